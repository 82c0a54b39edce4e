"""How well the scripted pusher pushes: success rate and contact share over seeded episodes.

    MUJOCO_GL=egl .venv/bin/python benchmarks/pusher_quality.py --episodes 50 --steps 50

Success: the object ends within FetchPush's 5 cm threshold of the goal. Contact share: the
fraction of steps with a non-zero gripper-object force. Also printed: the fraction of episodes
with contact that starts again after a gap (a re-approach, or the block bouncing off the fingers),
a sign that the data is not one straight push.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mmf_rl.envs.push import MultimodalPushEnv
from mmf_rl.envs.scripted import rollout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--image-size", type=int, default=64)
    args = parser.parse_args()

    env = MultimodalPushEnv(image_size=args.image_size)
    successes, contact_shares, reapproaches, push_distances = [], [], [], []
    start = time.perf_counter()
    try:
        for index in range(args.episodes):
            episode = rollout(env, args.seed, index, args.steps)
            in_contact = np.linalg.norm(episode["force"][:, :3], axis=1) > 0
            successes.append(episode["success"][-1])
            contact_shares.append(in_contact.mean())
            # A contact run that starts after an earlier one ended: the pusher lost the block and came back.
            reapproaches.append(np.count_nonzero(np.diff(in_contact.astype(int)) == 1) >= 2)
            xy = episode["object_pose"][:, :2]
            push_distances.append(np.linalg.norm(xy[-1] - xy[0]))
    finally:
        env.close()
    elapsed = time.perf_counter() - start
    print(f"episodes            {args.episodes} x {args.steps} steps (seed {args.seed})")
    print(f"success rate        {np.mean(successes):.1%}")
    print(f"steps in contact    {np.mean(contact_shares):.1%}")
    print(f"episodes w/ contact {np.mean(np.array(contact_shares) > 0):.1%}")
    print(f"contact resumed     {np.mean(reapproaches):.1%} of episodes (lost, then regained)")
    print(f"object travel       {np.mean(push_distances):.3f} m mean")
    print(f"time                {elapsed:.1f} s ({args.episodes / elapsed:.2f} episodes/s, one process)")


if __name__ == "__main__":
    main()
