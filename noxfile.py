"""Developer sessions: `nox -s tests` (the CI command: the whole suite), `nox -s quick` (the
quick loop: the suite without the end-to-end tests marked `slow`) and `nox -s lint`."""

from __future__ import annotations

import nox

nox.options.sessions = ["tests"]
nox.options.reuse_existing_virtualenvs = True

# torch goes in first, pinned to the version whose CPU wheel this machine holds locally (so
# the line gets a CPU build here; from the public index it would resolve to the CUDA build).
# Any recent torch works: elsewhere, install it from PyTorch's CPU index
# (--index-url https://download.pytorch.org/whl/cpu). The project's requirement is a range.
TORCH_PIN = "torch==2.13.0"
#: one BLAS thread per pytest worker (the workers are the parallelism)
TEST_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@nox.session
def tests(session: nox.Session) -> None:
    """Install the pinned CPU torch, then the project with test extras; run pytest."""
    session.install(TORCH_PIN)
    session.install("-e", ".[test]")
    args = session.posargs or ["-n", "2", "--dist", "loadfile", "-q", "--durations=15"]
    session.run("pytest", *args, env=TEST_ENV)


@nox.session
def quick(session: nox.Session) -> None:
    """The quick loop: every test not marked `slow` (no training, no verification of a real
    checkpoint, no Dask cluster, no CLI subprocess doing real work); extra pytest arguments
    after `--` are added."""
    session.install(TORCH_PIN)
    session.install("-e", ".[test]")
    session.run("pytest", "-m", "not slow", "-n", "2", "--dist", "loadfile", "-q",
                *session.posargs, env=TEST_ENV)


@nox.session
def lint(session: nox.Session) -> None:
    """ruff over the code."""
    session.install("ruff>=0.4")
    session.run("ruff", "check", "certify", "training", "reports", "tests", "bench", "noxfile.py")


@nox.session
def bench(session: nox.Session) -> None:
    """Run the benchmarks (each prints JSON lines)."""
    session.install(TORCH_PIN)
    session.install("-e", ".")
    for script in ("bench/train.py", "bench/verify.py", "bench/prove.py", "bench/lipsdp.py"):
        session.run("python", script)
