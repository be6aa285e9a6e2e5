"""Shared pieces of the command-line tests: a fast policy, a linear ground-truth checkpoint,
running `certify.cli.main.main` in-process with its exit code and both streams, and running it in
a fresh interpreter (`probe`: which heavy libraries it imported)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from certify.cli.main import main
from certify.model import checkpoint

from .planted import linear_problem

FAST_POLICY = """
[tool.certify]
grid_points = 20000
adversarial_starts = 8
adversarial_steps = 30
max_boxes = 100000
rate_boxes = 20000
residual_boxes = 20000
lipschitz_boxes = 20000
dissipation_boxes = 40000
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


ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "sympy", "cvxpy", "matplotlib", "scipy")
# runs the CLI in a fresh interpreter, then lists the heavy libraries it imported
PROBE = ("import sys; from certify.cli.main import main; rc = main(sys.argv[1:]); "
         f"print('IMPORTED', sorted(m for m in {HEAVY!r} if m in sys.modules)); sys.exit(rc)")


def fresh_env() -> dict[str, str]:
    """The environment for a child interpreter that imports this tree's certify."""
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": str(ROOT) + (os.pathsep + path if path else "")}


def probe(*argv: str, cwd: Path | None = None) -> tuple[int, str, str, list[str] | None]:
    """(exit code, stdout without the probe line, stderr, heavy modules imported) of
    `certify ARGV` in a fresh interpreter."""
    proc = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True,
                          text=True, timeout=300, cwd=cwd, env=fresh_env())
    lines = proc.stdout.splitlines()
    imported = eval(lines[-1].split(" ", 1)[1]) if lines and lines[-1].startswith("IMPORTED") \
        else None
    return proc.returncode, "\n".join(lines[:-1]), proc.stderr, imported
