"""certify: train and certify learned contraction observers.

Public API:
    load_system, System            -- system specs
    GainNetwork                    -- the gain network k(xhat, y)
    checkpoint.save / checkpoint.load
    Problem                        -- what is verified
    Status                         -- PROVED / VIOLATED / UNKNOWN / SKIPPED / ERROR
"""

from certify.errors import CertifyError, CheckpointError, SettingsError, SpecError
from certify.network import GainNetwork
from certify.problem import Problem
from certify.results import Status
from certify.system import System, load_system

__version__ = "0.1.0"

__all__ = [
    "CertifyError", "CheckpointError", "GainNetwork", "Problem", "SettingsError", "SpecError",
    "Status", "System", "load_system", "__version__",
]
