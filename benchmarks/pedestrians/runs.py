"""What the ETH/UCY benchmark's stages share: a fold's (or held-out pair's) windows as the benchmark
scores them, a model trained into its run directory, scores at the invocation's batch size and device.

``args`` is ``benchmarks/ethucy.py``'s parsed command line (``--data``, ``--out``, ``--window-set``,
``--batch-size``, ``--device``, ``--seed``, ``--select``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from benchmarks.pedestrians.recipe import IMAGE_SIZE, Budget, data_config_path, run_path, train_overrides

SCORED_SPLITS = ("val", "test")  # test for every row, val for the heading noise's std


def fold_config(args: argparse.Namespace, fold: str) -> dict:
    """A fold's (or a held-out pair's) data config dict, as the benchmark reads its windows."""
    import yaml

    config = yaml.safe_load(data_config_path(args, fold).read_text())
    return config | {"cache_dir": str(args.data / "cache"), "image_size": [IMAGE_SIZE, IMAGE_SIZE]}


def windows(args: argparse.Namespace, config: dict, scored: tuple[str, ...] = SCORED_SPLITS):
    """``config``'s windows (normalised with its training split), its ``scored`` splits cut to the
    invocation's window set."""
    from mmf_rl.datasets import DataConfig, WindowDataset, ethucy

    data = WindowDataset(DataConfig.from_dict(config))
    # Scoring reads the splits' windows from here; training reads its own WindowDataset of the config.
    for split in scored:
        data.split_windows[split] = ethucy.window_set_ids(data, split, args.window_set)
    return data


def fold_data(args: argparse.Namespace, fold: str):
    """The fold's windows (normalised with its training split), its val and test splits cut to the
    invocation's window set, and its data config dict."""
    config = fold_config(args, fold)
    return windows(args, config), config


def scene_data(args: argparse.Namespace, config: dict, scene: str):
    """``config``'s windows with ``scene``'s whole file as the test split (as its outer fold tests it),
    cut to the window set: a training scene held out, scored as the test scene is."""
    test = fold_config(args, scene)["split"]["test"]
    return windows(args, config | {"split": config["split"] | {"test": test}}, ("test",))


def val_curve(run_dir: Path) -> list[tuple[int, float]]:
    """``(step, val ADE in metres)`` the trainer logged at each of the budget's evaluations: the only
    evidence the budget is read from (the test scene is never looked at for it)."""
    path = run_dir / "logs" / "scalars" / "val" / "ade.csv"
    if not path.is_file():
        return []
    return [(int(float(s)), float(v)) for s, v in (row.split(",")[:2] for row in path.read_text().split())]


def score(model, data, split: str, args: argparse.Namespace, deterministic: bool = False, modes=None) -> dict:
    """``model``'s scores on ``split`` at the invocation's batch size and device, in ``modes`` (default
    all four)."""
    from benchmarks.pedestrians.scoring import MODES, score_split

    return score_split(
        model,
        data,
        split,
        args.batch_size,
        args.device,
        deterministic=deterministic,
        modes=tuple(modes or MODES),
    )


def train_run(
    args: argparse.Namespace, budget: Budget, fold: str, label: str, chosen: dict[str, str] | None
) -> tuple[object, float]:
    """Train ``label`` on ``fold`` (or a held-out pair) with ``chosen``'s options into its run directory,
    from nothing; the trained model and the seconds it took."""
    import shutil

    import mmf_rl
    from mmf_rl.configuration import compose_config
    from mmf_rl.models import load_trained_model

    run_dir = run_path(args, fold, label, chosen)
    if run_dir.exists():  # an interrupted run: start it again
        shutil.rmtree(run_dir)
    start = time.perf_counter()
    mmf_rl.train(compose_config("train", train_overrides(args, budget, fold, label, run_dir, chosen)))
    trained = time.perf_counter() - start
    model, _, _ = load_trained_model(run_dir / "checkpoints", map_location=args.device)
    return model, trained
