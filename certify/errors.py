"""Exceptions of certify.

Every error a user can cause (bad spec, bad checkpoint, bad settings) derives from
`CertifyError`; the command line turns it into one line on stderr and exit code 2.
"""

from __future__ import annotations


class CertifyError(Exception):
    """A problem with the user's input: one line, exit code 2."""


class SpecError(CertifyError):
    """A system spec (TOML or expression) is malformed."""


class CheckpointError(CertifyError):
    """A checkpoint file is missing, corrupt, of another format or version, or inconsistent."""


class SettingsError(CertifyError):
    """A setting (flag, `[tool.certify]` entry) is out of its allowed range."""


class SolverError(Exception):
    """A numerical solver failed in a way that is not the user's fault."""
