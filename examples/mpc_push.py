"""Model-predictive control of the multimodal push task with a trained world model.

    mmf-rl record --out data/push_explore --episodes 300 --seed 1 --exploration 0.1
    mmf-rl train experiment=world_model
    MUJOCO_GL=egl .venv/bin/python examples/mpc_push.py --checkpoint runs/world_model/checkpoints \
        --drop image --outage dies

Every step, the agent encodes the last H steps of whatever sensors work, samples candidate
action sequences, forecasts the object's motion under each with the world model (one batched
decode), refits its sampling distribution to the best ones a few times (CEM) and applies the
first action of the final mean. `--drop` makes a sensor fail, the
`--outage` way: off for whole episodes (`episode`, unplugged), in bursts of a few steps
(`bursts`), or dying at a random step and staying off until the episode ends (`dies`). The same
model keeps planning from the rest. benchmarks/mpc_push.py runs this over many episodes against
the scripted pusher.
"""

import argparse

import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv

from mmf_rl.envs.modality_dropout import ModalityDropout, UniformBursts
from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv
from mmf_rl.rl import PushObjective, SequenceCEMPlanner, WorldModel

# How the sensor fails, as benchmarks/mpc_push.py plays it: off for the whole episode; in outages of
# 2-8 steps starting with probability 0.2 at each step it is up; or for good after 1-49 steps.
OUTAGES = {
    "episode": {"outage": "episode", "outage_prob": 1.0},
    "bursts": {"outage": "bursts", "outage_prob": 0.2, "bursts": UniformBursts(2, 8)},
    "dies": {"outage": "dies", "outage_prob": 1.0, "dies_after": UniformBursts(1, 49)},
}

parser = argparse.ArgumentParser(description="MPC with a push world model")
parser.add_argument("--checkpoint", default="runs/world_model/checkpoints")
parser.add_argument("--episodes", type=int, default=5)
parser.add_argument("--drop", choices=["image", "force"], default=None, help="sensor that fails")
parser.add_argument("--outage", choices=list(OUTAGES), default="episode", help="how it fails")
parser.add_argument("--seed", type=int, default=0)
args = parser.parse_args()
torch.set_num_threads(2)

# The world model and the window of sensor history it reads.
world_model = WorldModel.from_checkpoint(args.checkpoint)
history = world_model.history_window()  # writes ("history", ...): the model's input window, every step

# The real env, rendering the camera at the size the model was trained on: the outage (if any) happens
# before the history sees the sensors.
transforms = [ModalityDropout([args.drop], seed=args.seed, **OUTAGES[args.outage])] if args.drop else []
image_size = next(m for m in world_model.modalities if m.name == "image").shape[-1]
env = TransformedEnv(
    MultimodalPushTorchEnv(image_size=image_size),
    Compose(*transforms, history, InitTracker()),
)

# The policy: CEM over whole action sequences, scored by the push objective.
planner = SequenceCEMPlanner(
    world_model,
    PushObjective(),
    env.action_spec,
    num_candidates=256,
    num_iterations=6,
    num_elites=32,
    seed=args.seed,
)

successes = 0
for episode in range(args.episodes):
    env.set_seed(args.seed + episode)
    rollout = env.rollout(50, planner, break_when_any_done=True)
    success = bool(rollout["next", "terminated"].any())
    successes += success
    distance = float(-rollout["next", "reward"][-1])
    print(
        f"episode {episode}: {'success' if success else 'failure'} after {rollout.shape[0]} steps, "
        f"object {100 * distance:.1f} cm from the goal"
    )
env.close()
print(
    f"success {successes}/{args.episodes} with "
    f"{'all sensors' if args.drop is None else f'{args.drop} failing ({args.outage})'}"
)
