"""Training of gain networks (the source method, reproduced faithfully, and fast).

Public API:
    TrainConfig, make_config, PRESETS    -- settings and named presets (`paper`, `tiny`)
    train, TrainResult, Objective        -- the training run and its objective
    collocation_points                   -- seeded uniform points in X x Y
    losses                               -- minor, eigenvalue and BC losses

The names are imported on first use (PEP 562), so that `certify train --help`, which reads
only the presets, does not import torch.
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> the module that defines it
_WHERE = {"losses": "training.losses", "collocation_points": "training.collocation",
          "Objective": "training.objective", "PRESETS": "training.presets",
          "TrainConfig": "training.presets", "make_config": "training.presets",
          "TrainResult": "training.train", "train": "training.train"}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'training' has no attribute {name!r}")
    module = importlib.import_module(_WHERE[name])
    return module if name == "losses" else getattr(module, name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
