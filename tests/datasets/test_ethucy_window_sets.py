"""ETH/UCY's window sets on a handful of synthetic tracks (no data needed; on the real files:
tests/datasets/test_ethucy.py)."""

import numpy as np
import pandas as pd

from mmf_rl.datasets import ethucy


def _walker(agent: int, frames: np.ndarray) -> pd.DataFrame:
    """``agent`` annotated at ``frames``, walking 1 m per step, as `ethucy.read_sequence` gives a file."""
    return pd.DataFrame({"frame": frames, "agent": agent, "x": frames / 10.0, "y": float(agent)})


def test_social_gan_keeps_a_window_only_with_another_agent_annotated_in_all_its_frames():
    """Agents 1 (21 steps) and 2 (20) share the 20 frames from frame 0; 3 misses one of them; 4 is alone
    in the 20 frames from 1000, where 5 misses a frame; 1's second window (from frame 10) is its own."""
    steps = np.arange(20) * ethucy.FRAME_STEP
    table = pd.concat(
        [
            _walker(1, np.arange(21) * ethucy.FRAME_STEP),
            _walker(2, steps),
            _walker(3, np.delete(steps, 5)),
            _walker(4, 1000 + steps),
            _walker(5, 1000 + np.delete(steps, 12)),
        ]
    ).sort_values(["frame", "agent"], ignore_index=True)
    windows = ethucy.track_windows(table)
    assert windows.values.tolist() == [[1, 0], [1, 10], [2, 0], [4, 1000]]  # none for 3 or 5
    kept = ethucy.social_gan_windows(windows["frame"].to_numpy())
    assert kept.tolist() == [True, False, True, False]
