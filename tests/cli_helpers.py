"""Shared pieces of the command-line tests: a fast policy, a linear ground-truth checkpoint,
and running `certify.cli.main` in-process with its exit code and both streams."""

from __future__ import annotations

import numpy as np

from certify import checkpoint
from certify.cli import main

from .planted import linear_problem

FAST_POLICY = """
[tool.certify]
grid_points = 20000
adversarial_starts = 8
adversarial_steps = 30
proof_seconds = 30
residual_seconds = 5
lipschitz_seconds = 5
sim_time = 1.0
sim_dt = 0.005
sim_initial_conditions = 2
"""

A = np.array([[0.0, 1.0], [-2.0, -3.0]])
C = np.array([[1.0, 0.0]])
K = np.array([[1.0], [-2.0]])


def save_problem(path, problem) -> str:
    checkpoint.save(path, system=problem.system, network=problem.network, lam=problem.lam,
                    P=problem.P)
    return str(path)


def save_linear(path, lam: float = 0.3) -> str:
    """A checkpoint whose gain is the exact linear injection K (y - C x): proved fast."""
    return save_problem(path, linear_problem(A, C, K, lam=lam))


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `certify ARGV`, run in this process."""
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err
