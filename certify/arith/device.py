"""The torch device the numeric kernels run on (`--device`, `[tool.certify] device`).

`cpu` is the default. `cuda` runs the MPDI grid sweep, the adversarial falsifier and the
branch-and-bound proofs (MPDI, rate, boundary residual, local Lipschitz) in float64 on the GPU
(`certify.checks.base.Context.on_device`, once per run: `Problem.on` moves the network and P;
points, boxes and every tensor of the enclosures are made on the device of their inputs,
which `tests/prove/test_device_follow.py` checks on the CPU by making the default device
`meta`). The simulation, the rate and residual
grids, LipSDP and the pre-flight stay on the CPU. Measured on an H100: the MPDI proof's box
bounds (README, "Scaling out"); the rate and side proofs on a GPU were not run there.

The outward rounding carries over unchanged: `torch.nextafter` is exact on CUDA as on the
CPU; +, -, *, / and sqrt are IEEE round-to-nearest there too (a fused multiply-add rounds
once, so it errs less, not more); CUDA's double-precision libm (tanh, exp, log: 1 ulp; sin,
cos, tan, pow, hypot: 2 ulps, CUDA C Programming Guide, "Mathematical Functions") stays inside
the 4-ulp widening of `certify.arith.intervals.ROUNDING`; Higham's gamma_k bounds of matrix products
and sums hold for any summation order, so cuBLAS's blocking is covered; the eigenvalue margins
need only a backward-stable symmetric eigensolver (cuSOLVER's, as LAPACK's) and the certified
Cholesky test only a Cholesky with the standard error bound.

A GPU pays for many boxes per round: `proof_batch` raises the round size there. Asking for
`cuda` where torch sees no CUDA device is bad input: one line, exit 2, before any work.
"""

from __future__ import annotations

import torch

from certify.errors import SettingsError

DEVICES = ("cpu", "cuda")


def resolve_device(name: str | None) -> torch.device:
    """`torch.device` for a setting value; `SettingsError` (exit 2) when it cannot be used."""
    name = "cpu" if name is None else str(name).strip().lower()
    base = name.split(":", 1)[0]
    if base not in DEVICES:
        raise SettingsError(f"--device must be one of {', '.join(DEVICES)}; got {name!r}")
    if base == "cuda":
        if not torch.cuda.is_available():
            raise SettingsError("--device cuda: torch sees no CUDA device on this machine "
                                f"(torch {torch.__version__}, built with CUDA "
                                f"{torch.version.cuda or 'none'}); use --device cpu")
        try:
            dev = torch.device(name)
        except RuntimeError as exc:
            raise SettingsError(f"--device {name}: {exc}") from None
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise SettingsError(f"--device {name}: only {torch.cuda.device_count()} CUDA "
                                "device(s) here")
        return dev
    return torch.device("cpu")


#: boxes per branch-and-bound round of the MPDI proof, by device type (a GPU evaluates a round
#: of many boxes in about the time of a few; the CPU's best is near the default)
PROOF_BATCH = {"cpu": 1024, "cuda": 16384}


def proof_batch(device: torch.device) -> int:
    """Boxes per round of the MPDI proof on `device` (`PROOF_BATCH`; 1024 elsewhere)."""
    return PROOF_BATCH.get(torch.device(device).type, 1024)


def describe(device: torch.device) -> str:
    """A short name for reports and benchmarks: 'cpu' or 'cuda:0 (NVIDIA H100 ...)'."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return "cpu"
