"""LeRobot datasets → forecasting windows (memory-mapped cache) → TensorDict batches.

from mmf_rl.datasets import DataConfig, WindowDataset
data = WindowDataset(DataConfig.from_dict(cfg))
for batch in data.loader("train", batch_size=64): ...
"""

from mmf_rl.datasets.augment import AugmentConfig, TrainingAugmentation
from mmf_rl.datasets.config import ActionConfig, DataConfig, ModalityConfig, TargetConfig
from mmf_rl.datasets.protocols import apply_presence_subset, presence_subsets, training_dropout
from mmf_rl.datasets.splits import Normalizer, split_episodes
from mmf_rl.datasets.windows import WindowDataset, WindowLoader

__all__ = [
    "ActionConfig",
    "AugmentConfig",
    "DataConfig",
    "TrainingAugmentation",
    "ModalityConfig",
    "Normalizer",
    "TargetConfig",
    "WindowDataset",
    "WindowLoader",
    "apply_presence_subset",
    "presence_subsets",
    "split_episodes",
    "training_dropout",
]
