"""Interval enclosures of the gain network, of D, and sound bounds on lam_max, over boxes.

Boxes live in z = (xhat, y) space: lo, hi of shape [B, d], d = n + p. Everything is batched
over boxes and sound under floating point (the rounding scheme is `certify.intervals.ROUNDING`).

Two enclosures of the (preconditioned) contraction matrix A(z) = M D(z) M^T are combined:

- plain interval: value, Jacobian (and second derivatives) of the MLP propagated layer by layer
  in interval arithmetic, pre-activations tightened by a mean-value form around the box centre;
- second-order (mean-value / Taylor) form: A(z) in A(c) + sum_m (z_m - c_m) [dA/dz_m](box).
  Writing [dA/dz_m] = G_m + [-R_m, R_m], lam_max(A(c) + sum_m d_m G_m) is convex in d, so its
  maximum over |d_m| <= r_m is attained at one of the 2^d vertices (small eigenproblems,
  vectorised); the remainder adds rho(sum_m r_m R_m + rad A(c)) (Weyl + Perron-Frobenius).

M is the identity for P = I; otherwise M ~ L^-1 (P = L L^T, computed in floating point and
then used as an exact matrix: by Sylvester's law of inertia D <= 0 iff M D M^T <= 0 for every
invertible M, so the float error of M costs tightness, never soundness).
"""

from certify.bounds.eigen import (  # noqa: F401
    MAX_VERTEX_DIM,
    _lam2_upper,
    _vertices,
    gershgorin_upper,
    lam_max_upper_interval,
    lam_max_upper_point,
    rho_upper,
    taylor_upper,
)
from certify.bounds.interval_ops import (  # noqa: F401
    bcast,
    const_lam,
    iadd,
    intersect,
    isum,
    isym,
    nan_min,
    point,
)
from certify.bounds.mpdi import BoxBounds, mpdi_box_bounds  # noqa: F401
from certify.bounds.network_interval import (  # noqa: F401
    GainEnclosure,
    NetEnclosure,
    gain_enclosure,
    network_enclosure,
)
from certify.bounds.preconditioner import (  # noqa: F401
    Preconditioner,
    _congruence,
    make_preconditioner,
    to_lam_max_D,
)
from certify.bounds.side import (  # noqa: F401
    dk_dy_box_upper,
    dk_dy_box_upper_crown,
    manifold_enclosure,
    residual_box_upper,
    residual_box_upper_crown,
)
from certify.bounds.taylor import (  # noqa: F401
    TM,
    jcl_taylor,
    network_taylor,
    tm_congruence,
    tm_lam_upper,
)
