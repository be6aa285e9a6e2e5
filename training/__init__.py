"""Training of gain networks (the source method, reproduced faithfully, and fast).

Public API:
    TrainConfig, make_config, PRESETS    -- settings and named presets (`paper`, `tiny`)
    train, TrainResult, Objective        -- the training run and its objective
    collocation_points                   -- seeded uniform points in X x Y
    losses                               -- minor, eigenvalue and BC losses
"""

from training import losses
from training.collocation import collocation_points
from training.objective import Objective
from training.presets import PRESETS, TrainConfig, make_config
from training.train import TrainResult, train

__all__ = ["PRESETS", "Objective", "TrainConfig", "TrainResult", "collocation_points",
           "losses", "make_config", "train"]
