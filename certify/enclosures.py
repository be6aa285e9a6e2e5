"""Interval enclosures of the gain network, of D, and sound bounds on lam_max, over boxes.

Boxes live in z = (xhat, y) space: lo, hi of shape [B, d], d = n + p. Everything is batched
over boxes and sound under floating point (the rounding scheme is `certify.intervals.ROUNDING`).

The implementation lives in `certify.bounds` (one module per job); this module re-exports it.
Enclosures of the (preconditioned) contraction matrix A(z) = M D(z) M^T, tried in stages per
box (`certify.bounds.mpdi.mpdi_box_bounds`), the smallest sound bound kept:

- plain interval (`bounds.network_interval`): value, Jacobian (and second derivatives) of the
  MLP propagated layer by layer in interval arithmetic, pre-activations tightened by a
  mean-value form around the box centre; a box it already decides skips the rest;
- first-order Taylor models (`bounds.taylor`): A(z) in c + sum_m g_m (z_m - c_m) + [-E, E];
  lam_max of the affine part is convex in z, so its maximum is at one of the 2^d vertices
  (small eigenproblems, vectorised); the remainder adds rho(E) or, for n <= 3, enters each
  vertex matrix entrywise (`bounds.eigen.hertz_upper`);
- backward linear bound propagation (`bounds.crown`, CROWN-style) through the Jacobian's
  computation graph with sound relaxations of tanh, tanh' and McCormick products
  (`bounds.relax`): per Jacobian entry, linear lower and upper functions of z, turned into a
  Taylor model and kept entry by entry where their remainder is smaller; tried where the
  Taylor model failed but a remainder shrunk by the network's measured gain would pass;
- with M = I and a direct network, the mixed rows P dN/dz in one backward pass
  (`bounds.mixed`), the last hidden layer's relaxation errors kept as a matrix P W_H eps
  and bounded in the Loewner order, x^T He{P W_H eps} x <= x^T W x
  (`bounds.structured`): the centre c + W of an upper model of A, not an entrywise
  remainder.

Eigenvalue bounds of interval matrices (`bounds.eigen`): exact closed form for n <= 2, else
the smallest of centre + radius (Weyl, Collatz-Wielandt), Gershgorin and the sign-pattern
vertex bound (Hertz) for n <= 6. In a decision (the MPDI proof, `mpdi_box_bounds(decide=True)`)
the vertex matrices of n >= 4 are tested against the level by a certified Cholesky
factorisation (`bounds.eigen.lam_max_at_most`) instead of eigenvalues, after Weyl's bound and
one test of the vertex most likely to fail, and again after a congruence by the box's own
room (lvl I - c)^(-1/2) where the remainder failed them (`bounds.decide`).

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
    IntervalDkDy,
    dk_dy_box_upper,
    dk_dy_box_upper_crown,
    dk_dy_interval,
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
