"""LeRobot datasets → forecasting windows (memory-mapped cache) → TensorDict batches.

    from mmf_rl.datasets import DataConfig, WindowDataset
    data = WindowDataset(DataConfig.from_dict(cfg))
    for batch in data.loader("train", batch_size=64): ...

Names are resolved on first use, so importing a submodule (e.g. the recorder) stays cheap.
"""

from importlib import import_module

_EXPORTS = {
    "AugmentConfig": "augment",
    "ImageAugmentation": "augment",
    "ActionConfig": "config",
    "DataConfig": "config",
    "ModalityConfig": "config",
    "TargetConfig": "config",
    "WindowDataset": "windows",
    "WindowLoader": "windows",
    "Normalizer": "splits",
    "split_episodes": "splits",
    "training_dropout": "protocols",
    "presence_subsets": "protocols",
    "apply_presence_subset": "protocols",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{_EXPORTS[name]}"), name)
