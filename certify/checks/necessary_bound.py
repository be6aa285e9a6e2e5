"""The sound upper bound of q over the output manifold, for linear h (vertex enclosures).

q = lam_max(Z^T (He{P Jf} + 2 lam P) Z) is lam_max of an affine function of Jf, hence convex
in Jf: on each sub-box of X it is at most its largest value at the vertices of the interval
enclosure of Jf there (`certify.checks.metric.enclosure_vertices`). Sub-boxes whose
h-enclosure misses Y are dropped. Floating-point error is carried as a margin added to the
bound: 64 n u (||S|| + 1) for LAPACK's eigenvalue error and the rounding in S, plus
3 z_err ||S|| for the kernel basis (within z_err of an exact orthonormal one, as in the
prover). The PROVED side of `certify.checks.necessary` (with the interval prover's
`bound_manifold_quantity` as a fallback).
"""

from __future__ import annotations

import math

import numpy as np

from certify.checks.metric import enclosure_vertices, kernel_values, output_matrix, sub_boxes
from certify.prove.side import kernel_basis_with_error
from certify.spec.system import System


def vertex_upper_bound(system: System, P: np.ndarray, lam: float, subdivisions: int | None = None
                       ) -> float | None:
    """Sound bound on max q over the manifold (linear h): q is lam_max of an affine function
    of Jf, hence convex in Jf, so on each sub-box it is at most its value at the vertices of
    the interval enclosure of Jf. Sub-boxes whose h-enclosure misses Y are dropped. A margin
    of 64 n u (||S|| + 1) covers LAPACK's eigenvalue error and the rounding in S."""
    if not system.h_is_linear:
        return None
    Z, z_err = kernel_basis_with_error(output_matrix(system))
    n = system.n
    if Z.shape[1] == 0:
        return -math.inf
    per = subdivisions or max(1, int(4096 ** (1.0 / n)))
    lo, hi = sub_boxes(system, per)
    if len(lo) == 0:
        return -math.inf
    relevant = np.repeat((np.abs(Z).sum(1) > 0)[None, :], n, axis=0)
    try:
        verts = enclosure_vertices(system, lo, hi, relevant)
    except ValueError:
        return None
    vals = kernel_values(verts.all, P, Z, lam)
    if not np.all(np.isfinite(vals)):
        return None
    Snorm = np.abs(P).sum() * np.abs(verts.all).max(initial=0.0) + 2 * abs(lam) * np.abs(P).sum()
    # 3 z_err ||S||: Z is within z_err of an exact orthonormal kernel basis (as in the prover)
    return float(vals.max() + 64 * n * np.finfo(float).eps * (Snorm + 1.0) + 3 * z_err * Snorm)
