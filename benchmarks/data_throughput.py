"""Windows/s of the cached window pipeline vs lerobot's own loader, on the same windows.

    .venv/bin/python benchmarks/data_throughput.py                 # records a small dataset
    .venv/bin/python benchmarks/data_throughput.py --root data/push
    mmf-rl bench data --data-config mine.yaml                      # any dataset: a data config
                                                                   # (mmf-rl inspect writes one)

The reference is ``LeRobotDataset(..., delta_timestamps=...)`` in a ``torch.utils.data.DataLoader``
reading exactly the windows the cache serves (same history, horizon, stride and features). The
cache's build time is compared with one lerobot pass over all windows (extrapolated from the
measured subset). The last line is ``ratio: N.Nx (cache W windows/s vs lerobot L windows/s)``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.synthetic.dataset import FORCE_FEATURE, IMAGE_FEATURE, POSE_FEATURE, STATE_FEATURE
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.windows import WindowDataset
from mmf_rl.log import configure_logging


def make_dataset(root: Path, episodes: int, steps: int, image_size: int, workers: int) -> str:
    """Record with the project's recorder when it exists, else write the synthetic dataset."""
    try:
        from mmf_rl.record import RecordConfig, record
    except ImportError:
        from benchmarks.synthetic.dataset import make_synthetic_dataset

        make_synthetic_dataset(root, [steps] * episodes, image_size=image_size)
        return "synthetic (mmf_rl.record is not available)"
    # No sensor faults: lerobot's shard aggregation stores NaN as parquet nulls, which the
    # reference loader (LeRobotDataset.__getitem__) cannot turn into tensors.
    record(RecordConfig(out=root, episodes=episodes, steps=steps, image_size=image_size, workers=workers))
    return "recorded with mmf_rl.record"


def cache_throughput(dataset: WindowDataset, batch_size: int, seconds: float) -> float:
    loader = dataset.loader("train", batch_size, seed=0)
    next(iter(loader))  # warm the page cache, like the reference's first batch
    windows, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for batch in loader:
            windows += batch.batch_size[0]
    return windows / (time.perf_counter() - start)


def lerobot_throughput(config: DataConfig, frame_indices: list[int], batch_size: int, workers: int) -> float:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    fps = LeRobotDataset(config.repo_id, root=config.root).fps
    step = config.stride / fps
    observed = [(i - config.history + 1) * step for i in range(config.history)]
    future = [k * step for k in range(1, config.horizon + 1)]
    delta_timestamps = {m.feature: observed for m in config.modalities.values()}
    delta_timestamps[config.target.feature] = future
    dataset = LeRobotDataset(config.repo_id, root=config.root, delta_timestamps=delta_timestamps)
    loader = torch.utils.data.DataLoader(
        torch.utils.data.Subset(dataset, frame_indices),
        batch_size=batch_size,
        shuffle=True,
        num_workers=workers,
        persistent_workers=False,
    )
    batches = iter(loader)
    first = next(batches)  # worker start-up and first decoders excluded, as for the cache
    windows, start = 0, time.perf_counter()
    for batch in batches:
        windows += len(batch["index"])
    elapsed = time.perf_counter() - start
    if windows == 0:
        raise SystemExit(f"--lerobot-windows must exceed one batch ({len(first['index'])} windows)")
    return windows / elapsed


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--root",
        type=Path,
        help="an existing LeRobot v3.0 dataset (default: record one); without "
        "--data-config it must have the push features",
    )
    parser.add_argument(
        "--data-config",
        type=Path,
        metavar="YAML",
        help="a data config (e.g. written by `mmf-rl inspect --write-config`) saying which features are "
        "the modalities and the target; default: the push dataset's features. Its root unless --root",
    )
    parser.add_argument(
        "--episodes", type=int, default=16, help="episodes to record when --root is not given"
    )
    parser.add_argument("--steps", type=int, default=60, help="frames per recorded episode")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--history", type=int, default=None, help="default: the data config's, else 10")
    parser.add_argument("--horizon", type=int, default=None, help="default: the data config's, else 10")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--lerobot-windows", type=int, default=384, help="windows the reference loader reads")
    parser.add_argument("--seconds", type=float, default=3.0, help="how long to time the cached loader")
    parser.add_argument(
        "--workers",
        type=int,
        default=min(2, len(os.sched_getaffinity(0))),
        help="recording processes and lerobot DataLoader workers",
    )
    parser.add_argument(
        "--decode-workers",
        type=int,
        default=None,
        help="cache build decode processes (default: a pool only for large datasets)",
    )
    return parser.parse_args(argv)


def data_config(args: argparse.Namespace, scratch: Path) -> DataConfig:
    """The user's data config (``--data-config``) or the push features of ``--root`` or of a dataset
    recorded into ``scratch``; every window in the train split, cached in ``scratch``."""
    if args.data_config is not None:
        from omegaconf import OmegaConf

        data = OmegaConf.to_container(OmegaConf.load(args.data_config), resolve=True)
        data.pop("defaults", None)
        root = args.root or data.get("root")
        if root is None:
            raise SystemExit(f"{args.data_config} has no `root`: pass --root DATASET")
    else:
        root = args.root
        if root is None:
            root = scratch / "push"
            made = make_dataset(root, args.episodes, args.steps, args.image_size, args.workers)
            print(f"dataset: {made} at {root}")
        data = {
            "image_size": [args.image_size, args.image_size],
            "modalities": {"image": IMAGE_FEATURE, "force": FORCE_FEATURE, "proprio": STATE_FEATURE},
            "target": {"feature": POSE_FEATURE, "dims": [0, 1]},
        }
    data.update(
        {
            "root": str(root),
            "cache_dir": str(scratch / "cache"),
            "split_fractions": [1.0, 0.0, 0.0],
            "missing": {},
        }
    )
    data.update({k: v for k, v in [("history", args.history), ("horizon", args.horizon)] if v is not None})
    return DataConfig.from_dict(data)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="mmf_rl_bench_") as scratch:
        config = data_config(args, Path(scratch))

        import lerobot.datasets.lerobot_dataset  # noqa: F401  (both sides need lerobot: keep its import out of the timing)

        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a user's --root may lack cameras: measured all the same
            dataset = WindowDataset(config, num_workers=args.decode_workers)
        build_s = time.perf_counter() - start
        cache_rate = cache_throughput(dataset, args.batch_size, args.seconds)

        ids = dataset.split_windows["train"]
        subset = ids[
            torch.randperm(len(ids), generator=torch.Generator().manual_seed(0))[: args.lerobot_windows]
        ]
        last_observed = dataset.window_start[subset] + (config.history - 1) * config.stride
        lerobot_rate = lerobot_throughput(config, last_observed.tolist(), args.batch_size, args.workers)

    one_pass_s = len(ids) / lerobot_rate
    modalities = ", ".join(f"{s.name} {s.kind} {list(s.shape)}" for s in dataset.specs)
    print(f"windows: {len(ids)} (H={config.history}, T={config.horizon}; {modalities})")
    print(
        f"cache build: {build_s:.1f} s vs one "
        f"lerobot pass over the same windows: {one_pass_s:.1f} s -> "
        f"{'no slower' if build_s <= one_pass_s else 'SLOWER'} ({one_pass_s / build_s:.1f}x)"
    )
    print(
        f"ratio: {cache_rate / lerobot_rate:.1f}x (cache {cache_rate:.0f} windows/s vs lerobot "
        f"{lerobot_rate:.0f} windows/s)"
    )


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    main()
