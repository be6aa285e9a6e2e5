"""Forward invariance of a plant region R, proved; and regions found around the attractor.

**What is proved.** A closed region R (`certify.spec.region.Region`) is forward invariant
for x' = f(x) when the flow crosses its boundary strictly inwards everywhere:

- a polygon (n = 2, simple, counter-clockwise): for every edge from p to q, with the
  outward normal a = (q2 - p2, -(q1 - p1)), a^T f(x) < 0 on the whole closed edge;
- a box: f_i < 0 on the face x_i = hi_i and f_i > 0 on the face x_i = lo_i (closed faces);
- a sublevel set R = {x in X : V(x) <= c}: grad V . f < 0 on {x in X : V(x) = c}, and
  V > c on the boundary of X (so R stays away from it).

Nagumo's argument: a trajectory leaving R leaves through a boundary point x*; there the flow
points strictly into every half-plane (polygon edge, box face) active at x* (into both at a
vertex, convex or not: near a convex vertex R is their intersection, near a reflex one their
union), or V decreases strictly through c, so x(t) is in R for small t after the exit time:
a contradiction. The strict inequalities are proved over the closed pieces, so vertices and
corners are covered.

**How.** Each condition is a function g < 0 over a parameter box (the edge parameter s in
[0, 1], a face, the box X), proved by branch and bound: g is enclosed over each piece in
outward-rounded interval arithmetic (`certify.spec.enclosures`; the Jacobian of f from
derivatives of f with its constants made exact rationals), as the smaller of the plain
enclosure and the mean-value form g(m) + g'(piece) (piece - m); a piece is closed when the
upper bound is < 0 (a sublevel piece also when V's enclosure excludes c), split in half
along its widest side otherwise. An edge's points p + s (q - p) are enclosed with q - p as
an interval and the normal as an interval vector, so rounding in either is covered.
VIOLATED needs a sound counterexample: a boundary point (in an enclosing box) where the
outward speed has a lower bound > 0 (for a sublevel set, a piece inside X where grad V . f
> 0 throughout that holds a point with V <= c and one with V > c: the level set crosses it
there and the flow leaves R). Everything else is UNKNOWN. NaN never closes a piece.

**Its reach.** The region's component ranges (`hull`) and h over it (`output_range`) are
bounded by covering R with boxes (those that provably miss R are dropped) and enclosing.

**Finding R** (`find_region`): the plant is simulated from points of X (by the caller's
integrator), and its attractor classified from the runs' tails: an equilibrium gets a
Lyapunov ellipse of its linearisation, {(x - x*)^T S (x - x*) <= c}, at the largest of a
few levels that proves; a cycle (n = 2) a polygon around it whose vertices sit on the
cycle's outward normals, at the smallest offsets for which every edge is crossed inwards at
sampled points (in flow order, each edge's exit vertex moved out until it is; repeated until
the loop closes), proved for 128 down to 32 edges, the tightest first. A candidate is only a
candidate: the prover decides.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import sympy
import torch

from certify.arith.intervals import Interval, down, imul, up
from certify.errors import SpecError
from certify.results import Status
from certify.spec.enclosures import enclose_list, f_enclosure, h_enclosure
from certify.spec.expr import evaluate
from certify.spec.interval_rules import INTERVAL
from certify.spec.region import Region, check_polygon, derivatives, exact_rationals

#: pieces bounded per round of a branch and bound (memory: a few tensors of this length)
ROUND_PIECES = 32_768
#: a piece narrower than this (relative to its parameter range) is not split again
MIN_WIDTH = 1e-10
#: leaves of the cover of R that bounds its ranges and h over it
COVER_LEAVES = 4096


# ----------------------------------------------------------------------------- results

@dataclass
class InvarianceProof:
    """The prover's answer for one region.

    `margin`: the largest proved upper bound of the outward speed over the boundary pieces
    (a^T f / |a| for a polygon, -+f_i for a box, grad V . f for a sublevel set; < 0 when
    PROVED); `witness`: a boundary point where the flow provably leaves R (VIOLATED);
    `hull` [n, 2]: outer bounds of R's component ranges; `output_range` [p, 2]: an outer
    enclosure of h over R; `boxes`: pieces bounded; `exhausted`: the budget ran out."""

    status: Status
    message: str
    margin: float | None = None
    witness: list[float] | None = None
    hull: np.ndarray | None = None
    output_range: np.ndarray | None = None
    boxes: int = 0
    exhausted: bool = False


@dataclass
class Search:
    """The outcome of one branch and bound over parameter pieces."""

    status: Status
    margin: float | None
    witness: np.ndarray | None
    boxes: int
    exhausted: bool
    owner: int | None = None


# ----------------------------------------------------------------------------- enclosures

_JACOBIANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def exact_jacobian(system: Any) -> list[sympy.Expr]:
    """df_i/dx_j (row-major) from f with every float constant an exact rational, so that the
    derivative is the derivative of the function f encloses (cached per system)."""
    cached = _JACOBIANS.get(system)
    if cached is None:
        exact = [exact_rationals(e) for e in system.f_expr]
        cached = [sympy.diff(e, s) for e in exact for s in system.symbols]
        _JACOBIANS[system] = cached
    return cached


def jacobian_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor) -> Interval:
    """Jf over boxes [B, n] -> Interval [B, n, n]."""
    a, b = enclose_list(system, exact_jacobian(system), lo, hi)
    n = system.n
    return Interval(a.reshape(-1, n, n), b.reshape(-1, n, n))


def _f(system: Any, box: Interval) -> Interval:
    return Interval(*f_enclosure(system, box.lo, box.hi))


def _dot(a: list[Interval], b: list[Interval]) -> Interval:
    out = imul(a[0], b[0])
    for x, y in zip(a[1:], b[1:]):
        out = out + imul(x, y)
    return out


def _shifts(lo: torch.Tensor, hi: torch.Tensor, m: torch.Tensor) -> Interval:
    """x - m over the box [lo, hi], rounded outward ([B, d])."""
    return Interval(down(lo - m), up(hi - m))


def _expr_enclosure(exprs: list[sympy.Expr], symbols: tuple, box: Interval) -> list[Interval]:
    env = {s: box[:, i] for i, s in enumerate(symbols)}
    like = box[:, 0]
    return [evaluate(e, env, INTERVAL, like) for e in exprs]


# ----------------------------------------------------------------------------- branch and bound

Bounder = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
Refuter = Callable[[torch.Tensor, torch.Tensor, torch.Tensor],
                   tuple[torch.Tensor, torch.Tensor]]


def prove_pieces(upper: Bounder, refute: Refuter, lo: torch.Tensor, hi: torch.Tensor,
                 owner: torch.Tensor, budget: int) -> Search:
    """Prove upper(piece) < 0 on every piece [lo, hi] [B, d] (owner [B]: which condition the
    piece belongs to; bounders see it), splitting pieces in half along their widest side
    relative to the starting pieces' widths (a side of width 0 stays whole): a small
    breadth-first branch and bound over low-dimensional parameter pieces, not the MPDI
    prover's `certify.search.bnb`.

    `upper(lo, hi, owner)` -> a sound upper bound [B] (-inf: the piece is closed without one;
    NaN: not closed); `refute(lo, hi, owner)` -> (lower [B], point [B, n]): lower > 0 proves
    a violation at the state `point`. Stops at the first violation (VIOLATED), when every
    piece is closed (PROVED), when a piece would be split below `MIN_WIDTH` of its start
    (UNKNOWN) or after `budget` pieces (UNKNOWN, `exhausted`); `margin` is the largest
    finite upper bound of the closed pieces."""
    scale = (hi - lo).max(0).values.clamp_min(1e-300)
    boxes, worst = 0, -math.inf
    while lo.shape[0]:
        if boxes >= budget:
            return Search(Status.UNKNOWN, None, None, boxes, True)
        take = min(lo.shape[0], ROUND_PIECES, budget - boxes)
        clo, chi, cown = lo[:take], hi[:take], owner[:take]
        lo, hi, owner = lo[take:], hi[take:], owner[take:]
        boxes += take
        ub = upper(clo, chi, cown)
        closed = ub < 0
        finite = closed & torch.isfinite(ub)
        if bool(finite.any()):
            worst = max(worst, float(ub[finite].max()))
        open_ = ~closed
        if not bool(open_.any()):
            continue
        olo, ohi, oown = clo[open_], chi[open_], cown[open_]
        low, point = refute(olo, ohi, oown)
        bad = low > 0
        if bool(bad.any()):
            k = int(torch.nonzero(bad)[0, 0])
            return Search(Status.VIOLATED, None, point[k].numpy(), boxes, False,
                          int(oown[k]))
        rel = (ohi - olo) / scale
        axis = torch.argmax(rel, dim=1)
        rows = torch.arange(olo.shape[0])
        if bool((rel[rows, axis] <= MIN_WIDTH).any()):
            return Search(Status.UNKNOWN, None, None, boxes, False)
        mid = 0.5 * (olo[rows, axis] + ohi[rows, axis])
        left_hi, right_lo = ohi.clone(), olo.clone()
        left_hi[rows, axis] = mid
        right_lo[rows, axis] = mid
        lo = torch.cat([lo, olo, right_lo])
        hi = torch.cat([hi, left_hi, ohi])
        owner = torch.cat([owner, oown, oown])
    return Search(Status.PROVED, worst, None, boxes, False)


# ----------------------------------------------------------------------------- polygon

@dataclass
class _Edges:
    """Per edge k (from vertex k to k + 1, counter-clockwise): the start P, the direction
    D = q - p and the outward normal A = (D2, -D1), as intervals [m, 2]; |A| rounded up."""

    P: Interval
    D: Interval
    A: Interval
    length: torch.Tensor

    @classmethod
    def of(cls, vertices: np.ndarray) -> _Edges:
        v = torch.as_tensor(vertices, dtype=torch.float64)
        q = torch.roll(v, -1, 0)
        P = Interval(v, v)
        D = Interval(down(q - v), up(q - v))
        A = Interval(torch.stack([D.lo[:, 1], -D.hi[:, 0]], 1),
                     torch.stack([D.hi[:, 1], -D.lo[:, 0]], 1))
        length = up(torch.sqrt(up((A.mag() ** 2).sum(1))))
        return cls(P, D, A, up(length))


def _edge_points(e: _Edges, own: torch.Tensor, s: Interval) -> Interval:
    """Enclosure of p + s (q - p) [B, 2] for parameter intervals s [B] on edges `own`."""
    P, D = e.P[own], e.D[own]
    step = imul(Interval(s.lo[:, None], s.hi[:, None]), D)
    return Interval(down(P.lo + step.lo), up(P.hi + step.hi))


def _edge_speed(system: Any, e: _Edges, own: torch.Tensor, s: Interval) -> Interval:
    """a^T f(p + s (q - p)) over parameter intervals s [B]: the plain enclosure."""
    x = _edge_points(e, own, s)
    F = _f(system, x)
    A = e.A[own]
    return _dot([A[:, 0], A[:, 1]], [F[:, 0], F[:, 1]])


def polygon_conditions(system: Any, vertices: np.ndarray) -> tuple[Bounder, Refuter, _Edges]:
    """The bounder and refuter of the edges' crossing conditions (parameter s in [0, 1])."""
    e = _Edges.of(vertices)

    def upper(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        s = Interval(lo[:, 0], hi[:, 0])
        plain = _edge_speed(system, e, own, s).hi
        m = 0.5 * (lo[:, 0] + hi[:, 0])
        at_m = _edge_speed(system, e, own, Interval(m, m))
        x = _edge_points(e, own, s)
        J = jacobian_enclosure(system, x.lo, x.hi)
        A, D = e.A[own], e.D[own]
        # g'(s) = a^T Jf(x(s)) (q - p)
        JD = [_dot([J[:, i, 0], J[:, i, 1]], [D[:, 0], D[:, 1]]) for i in range(2)]
        slope = _dot([A[:, 0], A[:, 1]], JD)
        mv = (at_m + imul(slope, _shifts(lo[:, 0], hi[:, 0], m))).hi
        # per unit normal: for a bound < 0, ub / |a|_up >= ub / |a| (still an upper bound)
        return torch.minimum(plain, mv) / e.length[own]

    def refute(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        m = 0.5 * (lo[:, 0] + hi[:, 0])
        speed = _edge_speed(system, e, own, Interval(m, m))
        point = _edge_points(e, own, Interval(m, m)).mid()
        return speed.lo, point

    return upper, refute, e


def prove_polygon(system: Any, vertices: np.ndarray, budget: int) -> Search:
    """Every edge of the counter-clockwise polygon `vertices` [m, 2] crossed inwards."""
    upper, refute, _ = polygon_conditions(system, vertices)
    m = vertices.shape[0]
    lo = torch.zeros(m, 1, dtype=torch.float64)
    hi = torch.ones(m, 1, dtype=torch.float64)
    return prove_pieces(upper, refute, lo, hi, torch.arange(m), budget)


# ----------------------------------------------------------------------------- box

def prove_box(system: Any, box: np.ndarray, budget: int) -> Search:
    """f_i < 0 on the face x_i = hi_i and f_i > 0 on x_i = lo_i, every face closed."""
    n = system.n
    b = torch.as_tensor(box, dtype=torch.float64)
    los, his = [], []
    for i in range(n):
        for side in (0, 1):
            lo, hi = b[:, 0].clone(), b[:, 1].clone()
            lo[i] = hi[i] = b[i, side]
            los.append(lo)
            his.append(hi)
    lo, hi = torch.stack(los), torch.stack(his)
    faces = torch.arange(2 * n)

    def signed(own: torch.Tensor, v: Interval) -> Interval:
        """-+ f_i of each face's row (outward speed: f_i on the upper face, -f_i on the
        lower)."""
        i, upper_face = own // 2, (own % 2) == 1
        rows = torch.arange(own.shape[0])
        lo_, hi_ = v.lo[rows, i], v.hi[rows, i]
        return Interval(torch.where(upper_face, lo_, -hi_), torch.where(upper_face, hi_, -lo_))

    def upper(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        box_ = Interval(lo, hi)
        plain = signed(own, _f(system, box_)).hi
        m = 0.5 * (lo + hi)
        at_m = signed(own, _f(system, Interval(m, m)))
        J = jacobian_enclosure(system, lo, hi)
        i = own // 2
        rows = torch.arange(own.shape[0])
        grad = Interval(J.lo[rows, i], J.hi[rows, i])  # [B, n]
        sh = _shifts(lo, hi, m)
        lin = _dot([grad[:, j] for j in range(n)], [sh[:, j] for j in range(n)])
        lin = Interval(torch.where((own % 2) == 1, lin.lo, -lin.hi),
                       torch.where((own % 2) == 1, lin.hi, -lin.lo))
        return torch.minimum(plain, (at_m + lin).hi)

    def refute(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        m = 0.5 * (lo + hi)
        return signed(own, _f(system, Interval(m, m))).lo, m

    return prove_pieces(upper, refute, lo, hi, faces, budget)


# ----------------------------------------------------------------------------- sublevel set

def _v_parts(region: Region, box: Interval) -> tuple[Interval, list[Interval]]:
    grad, _ = derivatives(region)
    V, *G = _expr_enclosure([region.V, *grad], region.symbols, box)
    return V, G


def prove_sublevel(system: Any, region: Region, X: np.ndarray, budget: int) -> Search:
    """grad V . f < 0 on {x in X : V(x) = level}: pieces of X whose V-enclosure excludes the
    level are closed, the others need a negative upper bound (plain, or mean value with
    d/dx (grad V . f) = H_V f + Jf^T grad V)."""
    n, c = system.n, float(region.level)  # type: ignore[arg-type]
    _, hess = derivatives(region)

    def vdot(box: Interval) -> tuple[Interval, list[Interval], Interval, Interval]:
        """V, grad V, f and grad V . f over boxes."""
        V, G = _v_parts(region, box)
        F = _f(system, box)
        return V, G, F, _dot(G, [F[:, i] for i in range(n)])

    def upper(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        box = Interval(lo, hi)
        V, G, F, plain = vdot(box)
        m = 0.5 * (lo + hi)
        at_m = vdot(Interval(m, m))[3]
        H = _expr_enclosure([h for row in hess for h in row], region.symbols, box)
        J = jacobian_enclosure(system, lo, hi)
        sh = _shifts(lo, hi, m)
        terms = []
        for j in range(n):  # d/dx_j (grad V . f) = sum_i H_ij f_i + sum_i G_i J_ij
            dj = _dot([H[i * n + j] for i in range(n)] + G,
                      [F[:, i] for i in range(n)] + [J[:, i, j] for i in range(n)])
            terms.append(imul(dj, sh[:, j]))
        lin = terms[0]
        for t in terms[1:]:
            lin = lin + t
        bound = torch.minimum(plain.hi, (at_m + lin).hi)
        away = (V.lo > c) | (V.hi < c)
        return torch.where(away, torch.full_like(bound, -math.inf), bound)

    def refute(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        speed = vdot(Interval(lo, hi))[3]
        # a corner with V <= c and one with V > c: the level set crosses the piece
        k = 2 ** min(n, 4)
        corners = torch.stack([torch.where(torch.tensor([(i >> j) & 1 for j in range(n)],
                                                        dtype=torch.bool), hi, lo)
                               for i in range(k)], 1)  # [B, K, n]
        flat = corners.reshape(-1, n)
        Vc = _expr_enclosure([region.V], region.symbols, Interval(flat, flat))[0]
        inside = (Vc.hi <= c).reshape(-1, k)
        outside = (Vc.lo > c).reshape(-1, k)
        crossed = inside.any(1) & outside.any(1)
        low = torch.where(crossed, speed.lo, torch.full_like(speed.lo, -math.inf))
        # the point shown: where V = c on the segment between the two corners (float
        # bisection, for the message; the proof is the piece)
        rows = torch.arange(lo.shape[0])
        a = corners[rows, torch.argmax(inside.to(torch.int8), 1)]
        b = corners[rows, torch.argmax(outside.to(torch.int8), 1)]
        for _ in range(30):
            m = 0.5 * (a + b)
            below = _expr_enclosure([region.V], region.symbols, Interval(m, m))[0].mid() <= c
            a = torch.where(below[:, None], m, a)
            b = torch.where(below[:, None], b, m)
        return low, 0.5 * (a + b)

    Xt = torch.as_tensor(X, dtype=torch.float64)
    return prove_pieces(upper, refute, Xt[None, :, 0].clone(), Xt[None, :, 1].clone(),
                            torch.zeros(1, dtype=torch.long), budget)


def prove_inside(region: Region, X: np.ndarray, budget: int) -> Search:
    """V > level on every face of X (so R = {x in X : V <= level} stays away from it)."""
    n, c = X.shape[0], float(region.level)  # type: ignore[arg-type]
    Xt = torch.as_tensor(X, dtype=torch.float64)
    los, his = [], []
    for i in range(n):
        for side in (0, 1):
            lo, hi = Xt[:, 0].clone(), Xt[:, 1].clone()
            lo[i] = hi[i] = Xt[i, side]
            los.append(lo)
            his.append(hi)

    def upper(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
        V = _expr_enclosure([region.V], region.symbols, Interval(lo, hi))[0]
        return down(c - V.lo)  # c - V < 0 <=> V > c; rounded towards "not closed"

    def refute(lo: torch.Tensor, hi: torch.Tensor, own: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        m = 0.5 * (lo + hi)
        V = _expr_enclosure([region.V], region.symbols, Interval(m, m))[0]
        return torch.where(V.hi <= c, torch.ones_like(V.hi), -torch.ones_like(V.hi)), m

    out = prove_pieces(upper, refute, torch.stack(los), torch.stack(his),
                           torch.arange(2 * n), budget)
    return out


# ----------------------------------------------------------------------------- cover

def _drops(region: Region) -> Callable[[Interval], torch.Tensor]:
    """Boxes that provably miss R: outside a half-plane holding the polygon (through an
    edge of its convex hull, offset to hold every vertex), or V > level throughout."""
    if region.kind == "sublevel":
        c = float(region.level)  # type: ignore[arg-type]
        return lambda box: _expr_enclosure([region.V], region.symbols, box)[0].lo > c
    if region.kind == "box":
        return lambda box: torch.zeros(box.lo.shape[0], dtype=torch.bool)
    v = np.asarray(region.vertices)
    hull = _convex_hull(v)
    e = _Edges.of(hull)
    V = torch.as_tensor(v, dtype=torch.float64)
    # offsets b_k >= max over vertices of a_k^T (v - p_k), rounded up
    offs = []
    for k in range(hull.shape[0]):
        A, P = e.A[k], e.P[k]
        rel = Interval(down(V - P.hi), up(V - P.lo))
        dots = _dot([Interval(A.lo[0].expand(len(v)), A.hi[0].expand(len(v))),
                     Interval(A.lo[1].expand(len(v)), A.hi[1].expand(len(v)))],
                    [rel[:, 0], rel[:, 1]])
        offs.append(float(dots.hi.max()))
    b = torch.tensor(offs, dtype=torch.float64)

    def drop(box: Interval) -> torch.Tensor:
        out = torch.zeros(box.lo.shape[0], dtype=torch.bool)
        for k in range(hull.shape[0]):
            A, P = e.A[k], e.P[k]
            rel = Interval(down(box.lo - P.hi), up(box.hi - P.lo))
            B = box.lo.shape[0]
            dots = _dot([Interval(A.lo[0].expand(B), A.hi[0].expand(B)),
                         Interval(A.lo[1].expand(B), A.hi[1].expand(B))],
                        [rel[:, 0], rel[:, 1]])
            out |= dots.lo > b[k]
        return out

    return drop


def _convex_hull(v: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of points [m, 2] (monotone chain; float decisions are
    harmless: the half-planes built on it are offset to hold every point)."""
    pts = sorted(map(tuple, v))

    def half(points: list) -> list:
        out: list = []
        for p in points:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper_ = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper_[:-1], dtype=np.float64)


def cover(system: Any, region: Region, root: np.ndarray, leaves: int = COVER_LEAVES
          ) -> tuple[np.ndarray, np.ndarray] | None:
    """Outer bounds of R's component ranges [n, 2] and of h over R [p, 2], from boxes that
    cover R: `root` (a box holding R) halved along the widest side while the count stays
    within `leaves`, boxes that provably miss R dropped. None when h is not finite there."""
    drop = _drops(region)
    lo = torch.as_tensor(root[:, 0], dtype=torch.float64)[None]
    hi = torch.as_tensor(root[:, 1], dtype=torch.float64)[None]
    for _ in range(64):
        keep = ~drop(Interval(lo, hi))
        lo, hi = lo[keep], hi[keep]
        if lo.shape[0] == 0 or 2 * lo.shape[0] > leaves:
            break
        axis = torch.argmax(hi - lo, dim=1)
        rows = torch.arange(lo.shape[0])
        mid = 0.5 * (lo[rows, axis] + hi[rows, axis])
        left_hi, right_lo = hi.clone(), lo.clone()
        left_hi[rows, axis] = mid
        right_lo[rows, axis] = mid
        lo, hi = torch.cat([lo, right_lo]), torch.cat([left_hi, hi])
    if lo.shape[0] == 0:
        return None
    ranges = np.stack([lo.min(0).values.numpy(), hi.max(0).values.numpy()], 1)
    hl, hh = h_enclosure(system, lo, hi)
    if not bool(torch.isfinite(hl).all() and torch.isfinite(hh).all()):
        return None
    return ranges, np.stack([hl.min(0).values.numpy(), hh.max(0).values.numpy()], 1)


# ----------------------------------------------------------------------------- one region

def prove_region(system: Any, region: Region, X: np.ndarray, budget: int) -> InvarianceProof:
    """Prove `region` forward invariant for x' = f(x) and bound its reach (see the module
    docstring); at most `budget` pieces in all."""
    what = region.describe()
    used = 0
    if region.kind == "sublevel":
        inside = prove_inside(region, X, budget)
        used += inside.boxes
        if inside.status != Status.PROVED:
            where = ("" if inside.witness is None else " at (" + ", ".join(
                f"{c:.6g}" for c in inside.witness) + ")")
            why = ("it reaches the boundary of X" + where if inside.status == Status.VIOLATED
                   else "V > level on the boundary of X was not proved within the budget")
            return InvarianceProof(Status.UNKNOWN, f"{what}: {why}", boxes=used,
                                   exhausted=inside.exhausted)
        search = prove_sublevel(system, region, X, budget - used)
        root = np.asarray(X, dtype=np.float64)
    elif region.kind == "polygon":
        search = prove_polygon(system, np.asarray(region.vertices), budget)
        root = region.bounding_box()
    else:
        search = prove_box(system, np.asarray(region.box), budget)
        root = region.bounding_box()
    used += search.boxes
    if search.status == Status.VIOLATED:
        point = [float(c) for c in search.witness]  # type: ignore[union-attr]
        where = ", ".join(f"{c:.6g}" for c in point)
        part = {"polygon": f"edge {search.owner}", "box": "a face",
                "sublevel": "the level set"}[region.kind]
        return InvarianceProof(Status.VIOLATED, f"{what} is not forward invariant: the flow "
                               f"leaves it across {part} at ({where}) (sound lower bound "
                               "of the outward speed > 0)", witness=point, boxes=used)
    if search.status != Status.PROVED:
        why = ("the budget ran out" if search.exhausted
               else "a piece could not be split further")
        return InvarianceProof(Status.UNKNOWN, f"{what}: the inward crossing was not proved "
                               f"({why}; {used} pieces)", boxes=used,
                               exhausted=search.exhausted)
    reach = cover(system, region, np.asarray(root, dtype=np.float64))
    hull = output = None
    if reach is not None:
        hull, output = reach
    margin = search.margin if search.margin is not None and math.isfinite(search.margin) \
        else None
    speed = "" if margin is None else f"; outward speed <= {margin:.3g} on its boundary"
    return InvarianceProof(Status.PROVED, f"{what} is forward invariant (the flow crosses "
                           f"its boundary inwards everywhere, proved{speed}; {used} pieces)",
                           margin=margin, hull=hull, output_range=output, boxes=used)


# ----------------------------------------------------------------------------- finding R

#: simulated time of the plant runs that locate the attractor, in units of the time scale
#: (the box's size over the flow's typical speed), and the fraction kept as the tail
SETTLE_SCALES = 60.0
TAIL_FRACTION = 0.25
#: plant runs from points of X
STARTS = 48
#: the polygons tried around a cycle (edges), tightest first
POLYGON_EDGES = (128, 64, 32)
#: sampled inward crossing required of a candidate edge (a^T f / (|a| |f|)), the tightest
#: polygons first
CROSSING = (-0.001, -0.003, -0.01)
#: the Lyapunov ellipse's levels tried, as fractions of the largest that fits in X
ELLIPSE_LEVELS = (0.5, 0.25, 0.1, 0.03, 0.01)

Simulate = Callable[[np.ndarray, float, int], np.ndarray]


@dataclass
class Attractor:
    """The plant's attractor as simulated: its kind ("equilibrium", "cycle", "other" or
    "none": every run blew up), the box of its samples [n, 2], the equilibrium [n] or one
    period of the cycle in time order [T, n]; and how it was found, in words."""

    kind: str
    box: np.ndarray | None = None
    point: np.ndarray | None = None
    orbit: np.ndarray | None = None
    note: str = ""
    samples: np.ndarray | None = field(default=None, repr=False)


def time_scale(system: Any, X: np.ndarray) -> float:
    """The box's width over the flow's median speed at points of X: the time in which the
    plant crosses a good part of the box (a simulation horizon's unit)."""
    rng = np.random.default_rng(0)
    pts = X[:, 0] + rng.random((256, X.shape[0])) * (X[:, 1] - X[:, 0])
    with np.errstate(all="ignore"):
        speed = np.linalg.norm(system.array_rows("f")(pts), axis=1)
    speed = speed[np.isfinite(speed)]
    med = float(np.median(speed)) if speed.size else 0.0
    width = float(np.linalg.norm(X[:, 1] - X[:, 0]))
    return width / med if med > 0 else 1.0


def locate_attractor(system: Any, X: np.ndarray, simulate: Simulate, seed: int = 0
                     ) -> Attractor:
    """Simulate the plant alone from `STARTS` points of X (`simulate(x0 [B, n], dt, steps)`
    -> [steps + 1, B, n]) and classify where the runs end up (`Attractor`)."""
    n = X.shape[0]
    rng = np.random.default_rng(seed)
    x0 = X[:, 0] + rng.random((STARTS, n)) * (X[:, 1] - X[:, 0])
    tau = time_scale(system, X)
    steps = 3000
    dt = SETTLE_SCALES * tau / steps
    runs = simulate(x0, dt, steps)
    scale = float(np.abs(X).max())
    tail = runs[int(steps * (1 - TAIL_FRACTION)):]
    ok = np.isfinite(tail).all((0, 2)) & (np.abs(tail).max((0, 2)) < 1e3 * scale)
    if not ok.any():
        return Attractor("none", note=f"every one of {STARTS} plant runs from X left any "
                         f"bounded region within {steps * dt:.3g} s")
    tail = tail[:, ok]
    flat = tail.reshape(-1, n)
    box = np.stack([flat.min(0), flat.max(0)], 1)
    note = (f"{int(ok.sum())} of {STARTS} plant runs from X, simulated {steps * dt:.3g} s; "
            f"their last {TAIL_FRACTION:.0%}")
    spread = np.abs(tail - tail[-1:]).max((0, 2))
    if float(spread.max()) <= 1e-4 * scale:
        ends = tail[-1]
        # the runs' end points around the point most of them reach
        centre = np.median(ends, axis=0)
        near = np.abs(ends - centre).max(1) <= 1e-3 * scale
        point = _refine_equilibrium(system, ends[near].mean(0) if near.any() else centre)
        return Attractor("equilibrium", box=box, point=point, samples=flat,
                         note=note + " settle at an equilibrium")
    if n == 2:
        orbit = _one_period(system, tail[:, int(np.argmax(spread))], simulate, dt)
        if orbit is not None:
            return Attractor("cycle", box=box, orbit=orbit, samples=flat,
                             note=note + " run around a cycle")
    return Attractor("other", box=box, samples=flat,
                     note=note + " neither settle at an equilibrium nor run around one cycle")


def _refine_equilibrium(system: Any, x: np.ndarray) -> np.ndarray:
    """A few Newton steps on f(x) = 0 from a simulated end point (kept if they converge)."""
    y = np.array(x, dtype=np.float64)
    for _ in range(8):
        xt = torch.as_tensor(y[None])
        F = system.f(xt)[0].numpy()
        J = system.jac_f(xt)[0].numpy()
        try:
            step = np.linalg.solve(J, F)
        except np.linalg.LinAlgError:
            return np.asarray(x, dtype=np.float64)
        y = y - step
    ok = np.all(np.isfinite(y)) and np.abs(y - x).max() <= 1e-2 * (1 + np.abs(x).max())
    return y if ok else np.asarray(x, dtype=np.float64)


def _one_period(system: Any, tail: np.ndarray, simulate: Simulate, dt: float
                ) -> np.ndarray | None:
    """One period of the cycle a run's tail [T, 2] goes around, at a fine step, in time
    order; None when the tail does not wind around its centre in one direction."""
    c = tail.mean(0)
    rel = tail - c
    if float(np.linalg.norm(rel, axis=1).min()) <= 1e-6 * float(np.abs(tail).max() + 1):
        return None
    ang = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    turns = (ang[-1] - ang[0]) / (2 * math.pi)
    if abs(turns) < 2 or np.any(np.sign(np.diff(ang)) == -np.sign(turns)):
        return None
    period = (len(tail) - 1) * dt / abs(turns)
    steps = 4000
    fine = simulate(tail[-1][None], 1.2 * period / steps, steps)[:, 0]
    a = np.unwrap(np.arctan2(fine[:, 1] - c[1], fine[:, 0] - c[0]))
    done = np.nonzero(np.abs(a - a[0]) >= 2 * math.pi)[0]
    if not done.size or not np.isfinite(fine).all():
        return None
    return fine[: int(done[0])]


def cycle_polygon(system: Any, orbit: np.ndarray, edges: int, crossing: float
                  ) -> np.ndarray | None:
    """A polygon of `edges` vertices around the cycle `orbit` [T, 2] (one period in time
    order), each vertex on the cycle's outward normal, at the smallest offsets for which
    every edge is crossed inwards at 64 sampled points (a^T f / (|a| |f|) <= `crossing`).
    Vertices are placed at equal steps of the flow's turning plus a third of the arc length
    (the chords then bend least from the flow). None when no offsets within the box's scale
    do."""
    f = system.array_rows("f")
    F = np.asarray(f(orbit), dtype=np.float64)
    speed = np.linalg.norm(F, axis=1)
    if not np.all(speed > 0):
        return None
    T = F / speed[:, None]
    turning = np.abs(np.diff(np.unwrap(np.arctan2(T[:, 1], T[:, 0]))))
    cum = np.concatenate([[0.0], np.cumsum(turning + np.linalg.norm(np.diff(orbit, axis=0),
                                                                    axis=1) / 3.0)])
    idx = np.searchsorted(cum, np.linspace(0.0, cum[-1], edges, endpoint=False))
    idx = np.minimum(idx, len(orbit) - 1)
    centre = orbit.mean(0)
    rel = orbit - centre
    clockwise = float(np.mean(rel[:, 0] * F[:, 1] - rel[:, 1] * F[:, 0])) < 0
    left = np.stack([-T[:, 1], T[:, 0]], 1)
    normal = (left if clockwise else -left)[idx]  # outward
    base = orbit[idx]
    scale = float(np.abs(orbit).max()) + 1.0
    step = 2e-3 * scale
    offset = np.full(edges, step)
    s = np.linspace(0.0, 1.0, 64)[:, None]

    def crossing_of(p: np.ndarray, q: np.ndarray) -> float:
        d = q - p
        a = np.array([-d[1], d[0]]) if clockwise else np.array([d[1], -d[0]])
        pts = p + s * d
        Fp = np.asarray(f(pts), dtype=np.float64)
        norm = np.linalg.norm(a) * np.maximum(np.linalg.norm(Fp, axis=1), 1e-300)
        return float(((Fp @ a) / norm).max())

    def crossed(k: int, j: int, off: float) -> bool:
        return crossing_of(base[k] + offset[k] * normal[k], base[j] + off * normal[j]) \
            <= crossing

    for _ in range(50):
        changed = False
        for k in range(edges):
            j = (k + 1) % edges
            if crossed(k, j, offset[j]):
                continue
            low, grow, high = offset[j], step, offset[j] + step
            while not crossed(k, j, high):  # outwards in growing steps, then back by halves
                low, grow = high, 1.5 * grow
                high = low + grow
                if high > 0.5 * scale:
                    return None
            for _ in range(10):
                mid = 0.5 * (low + high)
                low, high = (low, mid) if crossed(k, j, mid) else (mid, high)
            offset[j] = high
            changed = True
        if not changed:
            break
    else:
        return None
    vertices = base + offset[:, None] * normal
    return vertices


def ellipse_region(system: Any, point: np.ndarray, X: np.ndarray, fraction: float
                   ) -> Region | None:
    """The Lyapunov ellipse {(x - x*)^T S (x - x*) <= c} of the linearisation at the
    equilibrium `point` (A^T S + S A = -I, S rounded to 6 digits), c the `fraction` of the
    largest level whose ellipse fits in X; None when Jf(x*) is not Hurwitz or x* not in X."""
    n = X.shape[0]
    if np.any(point <= X[:, 0]) or np.any(point >= X[:, 1]):
        return None
    A = system.jac_f(torch.as_tensor(point[None]))[0].numpy()
    if not np.all(np.isfinite(A)) or float(np.linalg.eigvals(A).real.max()) >= 0:
        return None
    K = np.kron(np.eye(n), A.T) + np.kron(A.T, np.eye(n))
    S = np.linalg.solve(K, -np.eye(n).reshape(-1)).reshape(n, n)
    S = 0.5 * (S + S.T)
    S = np.array([[float(f"{v:.6g}") for v in row] for row in S])
    xs = np.array([float(f"{v:.9g}") for v in point])
    if float(np.linalg.eigvalsh(S).min()) <= 0:
        return None
    Sinv = np.diag(np.linalg.inv(S))
    room = np.minimum(xs - X[:, 0], X[:, 1] - xs)
    level = float(f"{fraction * float(np.min(room ** 2 / Sinv)):.6g}")
    if not level > 0:
        return None
    names = system.states
    shifted = [s if c == 0 else f"({s} - {float(c)!r})" if c > 0 else f"({s} + {-float(c)!r})"
               for s, c in zip(names, xs)]
    terms = []
    for i in range(n):
        for j in range(i, n):
            coef = float(S[i, i] if i == j else 2.0 * S[i, j])
            if coef:
                terms.append(f"{coef!r}*{shifted[i]}**2" if i == j
                             else f"{coef!r}*{shifted[i]}*{shifted[j]}")
    text = " + ".join(terms)
    syms = tuple(system.symbols)
    from certify.spec.region import parse_region

    try:
        region = parse_region({"V": text, "level": level}, X=X, states=list(names),
                              symbols=list(syms), where="the Lyapunov ellipse")
    except SpecError:
        return None
    return Region("sublevel", V_text=region.V_text, level=region.level, V=region.V,
                  symbols=region.symbols, origin="found")


def polygon_region(vertices: np.ndarray) -> Region | None:
    """A found polygon as a `Region` (None when it is not a simple polygon)."""
    wide = np.array([[-np.inf, np.inf], [-np.inf, np.inf]])
    try:
        v = check_polygon(vertices, wide, "the polygon found")
    except SpecError:
        return None
    return Region("polygon", vertices=v, origin="found")


def candidates(system: Any, attractor: Attractor, X: np.ndarray
               ) -> Iterator[tuple[Region, str]]:
    """Regions to try around the attractor, most useful first (made one at a time, as the
    caller asks), each with a word on how it was made."""
    if attractor.kind == "equilibrium" and attractor.point is not None:
        for frac in ELLIPSE_LEVELS:
            r = ellipse_region(system, attractor.point, X, frac)
            if r is not None:
                yield r, f"Lyapunov ellipse at {frac:g} of the largest level in X"
    elif attractor.kind == "cycle" and attractor.orbit is not None:
        for crossing in CROSSING:
            for edges in POLYGON_EDGES:
                v = cycle_polygon(system, attractor.orbit, edges, crossing)
                r = None if v is None else polygon_region(v)
                if r is not None:
                    yield r, f"polygon of {edges} edges around the cycle"
