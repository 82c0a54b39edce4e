"""mmf-rl: multimodal forecasters that stay accurate when sensors go missing.

The Python entry points of the commands: :func:`train` (``mmf-rl train``) and :func:`evaluate`
(``mmf-rl eval``). Both are imported on first use, so that ``import mmf_rl`` (and ``mmf-rl --help``)
does not load torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mmf_rl.eval.evaluation import evaluate
    from mmf_rl.trainers.training import train

__version__ = "0.1.0"
__all__ = ["__version__", "evaluate", "train"]

# public name -> the module that defines it
_ENTRY_POINTS = {"train": "mmf_rl.trainers.training", "evaluate": "mmf_rl.eval.evaluation"}


def __getattr__(name: str):
    if name not in _ENTRY_POINTS:
        raise AttributeError(f"module 'mmf_rl' has no attribute {name!r}")
    value = getattr(importlib.import_module(_ENTRY_POINTS[name]), name)
    globals()[name] = value  # imported once
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
