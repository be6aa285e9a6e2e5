"""certify: train and certify learned contraction observers.

Public API:
    load_system, System            -- system specs
    GainNetwork                    -- the gain network k(xhat, y)
    checkpoint.save / checkpoint.load
    Problem                        -- what is verified
    verify, VerifySettings         -- run every check -> Certificate (never prints or exits)
    Certificate, exit_code         -- the result, its JSON form and the CLI exit code
    Status                         -- PROVED / PASSED / VIOLATED / UNKNOWN / SKIPPED / ERROR

Names are imported on first use (PEP 562), so that `import certify` and the command line
start without loading torch, sympy or cvxpy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> the module that defines it (None: the name is that module)
_PUBLIC = {
    "Certificate": "certify.certificate", "exit_code": "certify.certificate",
    "CertifyError": "certify.errors", "CheckpointError": "certify.errors",
    "SettingsError": "certify.errors", "SpecError": "certify.errors",
    "GainNetwork": "certify.model.network", "Problem": "certify.model.problem",
    "Status": "certify.results", "VerifySettings": "certify.settings",
    "System": "certify.spec.system", "load_system": "certify.spec.system",
    "verify": "certify.verify", "checkpoint": None,
}

__all__ = [
    "Certificate", "CertifyError", "CheckpointError", "GainNetwork", "Problem", "SettingsError",
    "SpecError", "Status", "System", "VerifySettings", "__version__", "checkpoint", "exit_code",
    "load_system", "verify",
]


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'certify' has no attribute {name!r}")
    module = _PUBLIC[name]
    value = (importlib.import_module(f"certify.{name}") if module is None
             else getattr(importlib.import_module(module), name))
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from certify.certificate import Certificate, exit_code
    from certify.errors import CertifyError, CheckpointError, SettingsError, SpecError
    from certify.model import checkpoint
    from certify.model.network import GainNetwork
    from certify.model.problem import Problem
    from certify.results import Status
    from certify.settings import VerifySettings
    from certify.spec.system import System, load_system
    from certify.verify import verify
