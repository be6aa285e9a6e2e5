"""Batched symmetric eigensolvers that behave alike on the CPU and on a GPU.

On the CPU these are `torch.linalg.eigvalsh` / `eigh` (LAPACK; an error, e.g. no convergence,
is raised to the caller as before). On a GPU torch calls cuSOLVER's batched solvers, which
failed on an H100 (torch 2.11, CUDA 13: CUSOLVER_STATUS_INTERNAL_ERROR) for a batch of
131,072 6x6 matrices while 32,768 ran; so the batch is cut into chunks of `GPU_CHUNK`
matrices, and a chunk the GPU solver still refuses is solved on the CPU instead. The margins
that make eigenvalues sound (`certify.arith.eigen`) need only a backward-stable solver,
which both are.
"""

from __future__ import annotations

import torch

#: matrices per batched eigensolver call on a GPU (module docstring)
GPU_CHUNK = 32768


def chunked(fn, S: torch.Tensor, chunk: int = GPU_CHUNK, fallback=None):
    """fn over S [..., n, n] in chunks of `chunk` matrices; a chunk on which fn raises
    RuntimeError goes to `fallback` (default: fn on a CPU copy, moved back). fn returns
    values [m, n] or a tuple (values [m, n], vectors [m, n, n])."""
    if fallback is None:
        def fallback(part: torch.Tensor):
            out = fn(part.cpu())
            return (tuple(t.to(part.device) for t in out) if isinstance(out, tuple)
                    else out.to(part.device))
    n = S.shape[-1]
    parts = []
    for part in S.reshape(-1, n, n).split(chunk):
        try:
            parts.append(fn(part))
        except RuntimeError:  # the GPU solver refused this chunk
            parts.append(fallback(part))
    batch = S.shape[:-2]
    if isinstance(parts[0], tuple):
        values = torch.cat([p[0] for p in parts]).reshape(*batch, n)
        vectors = torch.cat([p[1] for p in parts]).reshape(*batch, n, n)
        return values, vectors
    return torch.cat(parts).reshape(*batch, n)


def _batched(fn, S: torch.Tensor):
    if S.device.type == "cpu" or S.numel() == 0:
        return fn(S)
    return chunked(fn, S)


def eigvalsh(S: torch.Tensor) -> torch.Tensor:
    """Eigenvalues (ascending) of symmetric matrices [..., n, n] (lower triangle used)."""
    return _batched(torch.linalg.eigvalsh, S)


def eigh(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(eigenvalues ascending [..., n], eigenvectors as columns [..., n, n]) of symmetric
    matrices [..., n, n] (lower triangle used)."""
    return _batched(lambda A: tuple(torch.linalg.eigh(A)), S)


#: `certify.model.kernels.lam_max` (n = 2) and `certify.arith.eigen._lam2_upper` switch to their
#: cancellation-free forms where a negative diagonal entry is more than this many times
#: larger in magnitude than the other diagonal entry and the off-diagonal one (the eigenvalue
#: then lies at the small entries' scale, which the textbook form rounds away)
SPREAD = 2.0**26


def dwarfed(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Where the 2 x 2 symmetric [[a, b], [b, c]] has a negative diagonal entry that dwarfs
    the other entries (SPREAD), and those are not both 0: bool, same shape (False where any
    entry is NaN)."""
    big = torch.maximum(a.abs(), c.abs())
    small = torch.maximum(torch.minimum(a.abs(), c.abs()), b.abs())
    negative = torch.where(a.abs() >= c.abs(), a, c) < 0
    return negative & (small > 0) & (big > SPREAD * small)
