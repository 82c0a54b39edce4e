"""DAgger for the push BC policies, with the scripted pusher as the expert.

A round of DAgger (Ross, Gordon and Bagnell, 2011) rolls out the learner, asks the expert what it
would have done in every state the learner visited, adds those labelled states to the
demonstrations and retrains on the union. Here the learner is a `BCPolicy` in the push env with
every sensor, reading what it reads in the test (`benchmarks.push.bc_evaluation.bc_env`); the expert is
the pusher that recorded the demonstrations in its state-only form (`MarkovPusher`), which reads
the full state (the object's pose, emitted by the env beside the sensors, never read by the
policy). DAgger assumes an expert policy of the state; the recording pusher is a state machine
(approach, push, retreat) whose phase follows the trajectory it drove, and along the learner's
trajectory that phase no longer matches the state, so it labelled one state with contradictory
actions. `MarkovPusher` infers its phase from each state: its label at a state is the same
whatever happened before.

`labelled_episodes` plays the seeded episodes; `demonstration_frames` keeps of each what
`Demonstrations.with_episodes` adds (the expert's action as the one to imitate); `save_episodes`
and `load_episodes` keep a round's episodes on disk, so a re-run does not play them again.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import TransformedEnv

from benchmarks.push.closed_loop import ScriptedPolicy, episode_result, episode_steps
from mmf_rl.envs.scripted import MarkovPusher
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE
from mmf_rl.keys import ModalitySpec
from mmf_rl.rl.demonstrations import ACTION

logger = logging.getLogger(__name__)

EXPERT_ACTION = "expert_action"  # the expert's action at the state, beside the learner's "action"
# The env seeds of round r's episodes start at seed + r * ROUND_SEEDS: never those of the test
# episodes (seed + i, i < ROUND_SEEDS) or of another round.
ROUND_SEEDS = 10_000
# Names the expert in the directories of saved rounds: episodes labelled by an earlier expert (the
# stateful pusher) are never read back as this one's.
EXPERT_NAME = "markov"
_RESULTS_FILE = "episodes.json"


def round_seed(seed: int, round_: int) -> int:
    """The env seed of the first episode of DAgger round ``round_`` (from 1) of an experiment whose
    test episodes start at ``seed``."""
    if round_ < 1:
        raise ValueError(f"DAgger rounds count from 1, found {round_}")
    return seed + ROUND_SEEDS * round_


class ExpertLabelled:
    """Acts with ``learner``; writes beside its ``"action"`` the ``expert``'s at the same state
    (`EXPERT_ACTION`). The expert is called first, on every step."""

    def __init__(self, learner, expert):
        self.learner, self.expert = learner, expert

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        label = self.expert(tensordict).get(ACTION).clone()
        return self.learner(tensordict).set(EXPERT_ACTION, label)


@torch.no_grad()
def labelled_episodes(
    env: TransformedEnv, learner, episodes: int, seed: int, max_steps: int | None = None
) -> Iterator[tuple[TensorDictBase, dict]]:
    """``episodes`` episodes of ``learner`` in ``env`` (episode ``i`` reset with seed ``seed + i``, as
    `benchmarks.push.closed_loop.play`), each step labelled by the scripted pusher as a function of the
    state (`MarkovPusher`). Yields each episode's rollout (``EXPERT_ACTION`` beside the
    learner's ``"action"``) and its `episode_result`. ``env`` needs an ``InitTracker`` (`bc_env`'s
    env has one); ``max_steps``: default the env's time limit."""
    actor = ExpertLabelled(learner, ScriptedPolicy(seed, MarkovPusher()))
    steps = episode_steps(env) if max_steps is None else max_steps
    for i in range(episodes):
        env.set_seed(seed + i)  # applied at the next reset
        rollout = env.rollout(steps, actor, break_when_any_done=True)
        yield rollout, episode_result(rollout)


def demonstration_frames(rollout: TensorDictBase, specs: Sequence[ModalitySpec]) -> TensorDict:
    """What `Demonstrations.with_episodes` adds of a labelled rollout: each modality's raw
    observation and presence as the env emitted them, the goal and the object's pose, and the
    expert's action as the ``"action"`` to imitate (the policy's own windows and forecasts are
    rebuilt from these)."""
    frames = TensorDict(batch_size=rollout.batch_size)
    for spec in specs:
        frames.set(spec.obs_key, rollout.get(spec.obs_key))
        frames.set(spec.present_key, rollout.get(spec.present_key))
    frames.set(GOAL, rollout.get(GOAL))
    frames.set(OBJECT_POSE, rollout.get(OBJECT_POSE))
    frames.set(ACTION, rollout.get(EXPERT_ACTION))
    return frames.clone()  # its own storage, not views of the whole rollout's


def save_episodes(directory: Path, episodes: Sequence[TensorDictBase], results: Sequence[dict]) -> None:
    """Write a round's episodes (`demonstration_frames`) and their results to ``directory``,
    atomically: it appears complete or not at all."""
    directory = Path(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.partial-", dir=directory.parent))
    try:
        torch.cat(list(episodes)).memmap(staging / "frames")
        (staging / _RESULTS_FILE).write_text(json.dumps(list(results), indent=2))
        os.replace(staging, directory)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def load_episodes(directory: Path) -> tuple[list[TensorDict], list[dict]] | None:
    """The episodes and results `save_episodes` wrote to ``directory``; ``None`` if it has none."""
    directory = Path(directory)
    if not (directory / _RESULTS_FILE).is_file():
        return None
    results = json.loads((directory / _RESULTS_FILE).read_text())
    frames = TensorDict.load_memmap(directory / "frames").to_tensordict()
    episodes = list(frames.split([r["steps"] for r in results]))
    logger.info("DAgger: %d labelled episodes read from %s", len(episodes), directory)
    return episodes, results
