"""certify: train and certify learned contraction observers.

Public API:
    load_system, System            -- system specs
    GainNetwork                    -- the gain network k(xhat, y)
    checkpoint.save / checkpoint.load
    Problem                        -- what is verified
    verify, VerifySettings         -- run every check -> Certificate (never prints or exits)
    Certificate, exit_code         -- the result, its JSON form and the CLI exit code
    Status                         -- PROVED / PASSED / VIOLATED / UNKNOWN / SKIPPED / ERROR
"""

from certify import checkpoint
from certify.certificate import Certificate, exit_code
from certify.errors import CertifyError, CheckpointError, SettingsError, SpecError
from certify.network import GainNetwork
from certify.problem import Problem
from certify.results import Status
from certify.settings import VerifySettings
from certify.system import System, load_system
from certify.verify import verify

__version__ = "0.1.0"

__all__ = [
    "Certificate", "CertifyError", "CheckpointError", "GainNetwork", "Problem", "SettingsError",
    "SpecError", "Status", "System", "VerifySettings", "__version__", "checkpoint", "exit_code",
    "load_system", "verify",
]
