"""Sound linear relaxations of the activation f, of f' and of products s * t, on intervals.

`relax_value(act, lo, hi)` and `relax_slope(act, lo, hi)` give parallel-line bounds of f and
f' (`LinearBounds`, the `certify.model.activations` contract): for tanh the tighter curvature-aware
bounds below (`relax_tanh`, `relax_dtanh`), for every other activation its own generic bounds
(`Activation.relax`, `Activation.relax_d1`: chord line plus an outward-rounded enclosure of
the residual over sub-intervals; sound by the same contract: the intercepts hold for the
real-number lines).

Method (per element, vectorised): a candidate slope a (the chord slope), then the intercepts
are the sound minimum and maximum of the residual r(x) = f(x) - a x over [lo, hi]. The residual
is split into pieces of known curvature (tanh: convex on x <= 0, concave on x >= 0; tanh':
convex for |x| >= c, concave for |x| <= c, c = atanh(1/sqrt 3), with the boundary moved 1e-9
outwards on each side and the sliver between evaluated by plain interval arithmetic). On a
convex piece the maximum is at an endpoint and the minimum is bounded below by the tangent at
any point x0 of the piece, r(x) >= r(x0) + r'(x0)(x - x0); on a concave piece the reverse. x0
is an approximate critical point (closed forms; for tanh' the roots of a cubic in tanh x),
which only affects tightness. Rounding: every r(.) and r'(.) value is an outward-rounded interval
(`certify.arith.intervals` rules: libm widened by 4 ulps, +, -, * one ulp outward), so the returned
intercepts hold for the real-number lines a x + b; users of the lines account for the float
evaluation of a x + b themselves.

McCormick (products): for s in [sl, su], t in [tl, tu], planes with the slopes of the averaged
McCormick estimators, s t >= tc s + sc t + bl and s t <= tc s + sc t + bu (sc, tc the float
midpoints, shared by both sides). g(s, t) = s t - tc s - sc t is bilinear, so its extremes over
the box are at the four corners: bl, bu are the min / max of outward-rounded corner values (for
exact midpoints bl = -(sl tl + su tu) / 2 and bu = -(sl tu + su tl) / 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from certify.arith.intervals import Interval, down, imul, up
from certify.model.activations import Activation
from certify.model.activations.base import LinearBounds  # one type for every relaxation
from certify.model.activations.tanh import d2tanh_enclosure, dtanh_enclosure, tanh_enclosure

_C_D1 = math.atanh(1.0 / math.sqrt(3.0))  # inflection points of tanh' (zeros of tanh''')
_GAP = 1e-9


def _f_and_df(kind: str, x: Interval) -> tuple[Interval, Interval]:
    """Enclosures of f and f' over x (kind 'tanh' or 'dtanh')."""
    if kind == "tanh":
        return tanh_enclosure(x), dtanh_enclosure(x)
    return dtanh_enclosure(x), d2tanh_enclosure(x)


def _residual(kind: str, x: torch.Tensor, a: torch.Tensor, slope: bool = True
              ) -> tuple[Interval, Interval | None]:
    """r(x) = f(x) - a x and (slope) r'(x) = f'(x) - a at points x (outward-rounded
    intervals); without `slope` r' is not computed (None)."""
    xi = Interval(x, x)
    if slope:
        f, df = _f_and_df(kind, xi)
    else:
        f, df = _f_point(kind, x), None
    r = _minus_ax(f, a, x, x)
    dr = None if df is None else Interval(down(df.lo - a), up(df.hi - a))
    return r, dr


def _f_point(kind: str, x: torch.Tensor) -> Interval:
    """Enclosure of f at points x (one libm call)."""
    xi = Interval(x, x)
    return tanh_enclosure(xi) if kind == "tanh" else dtanh_enclosure(xi)


def _minus_ax(f: Interval, a: torch.Tensor, xa: torch.Tensor, xb: torch.Tensor) -> Interval:
    """f - a x for x in [xa, xb] (f an enclosure of f over it), rounded outward; for a point
    x (xa is xb) the float product a x is within one ulp of the real one."""
    if xa is xb:
        ax = a * xa
        return Interval(down(f.lo - up(ax)), up(f.hi - down(ax)))
    ax = imul(Interval(a, a), Interval(xa, xb))
    return Interval(down(f.lo - ax.hi), up(f.hi - ax.lo))


_CONSTS: dict[tuple[str, float, float], tuple[float, float]] = {}


def _const_f(kind: str, lo: float, hi: float) -> tuple[float, float]:
    """Enclosure of f over the fixed interval [lo, hi] (a piece boundary when lo = hi, or a
    sliver), computed once and cached."""
    key = (kind, lo, hi)
    if key not in _CONSTS:
        lt = torch.tensor([lo], dtype=torch.float64, device="cpu")
        ht = lt if lo == hi else torch.tensor([hi], dtype=torch.float64, device="cpu")
        f = (tanh_enclosure if kind == "tanh" else dtanh_enclosure)(Interval(lt, ht))
        _CONSTS[key] = (float(f.lo[0]), float(f.hi[0]))
    return _CONSTS[key]


class _Ends:
    """f at the interval ends lo, hi, computed once per relaxation and shared by its pieces
    (a piece's end is lo / hi, or the piece's fixed boundary where it clamps them)."""

    def __init__(self, kind: str, lo: torch.Tensor, hi: torch.Tensor) -> None:
        self.kind, self.lo, self.hi = kind, lo, hi
        self.f_lo, self.f_hi = _f_point(kind, lo), _f_point(kind, hi)

    def restrict(self, mask: torch.Tensor) -> _Ends:
        """The same ends on the elements `mask` selects (no libm call again)."""
        sub = _Ends.__new__(_Ends)
        sub.kind, sub.lo, sub.hi = self.kind, self.lo[mask], self.hi[mask]
        sub.f_lo = Interval(self.f_lo.lo[mask], self.f_lo.hi[mask])
        sub.f_hi = Interval(self.f_hi.lo[mask], self.f_hi.hi[mask])
        return sub

    def clamped(self, f_end: Interval, clamp: torch.Tensor, p: float) -> Interval:
        """f at the end, or at the boundary p where `clamp` (the end lies beyond p)."""
        if not math.isfinite(p):
            return f_end
        plo, phi = _const_f(self.kind, p, p)
        return Interval(torch.where(clamp, plo, f_end.lo), torch.where(clamp, phi, f_end.hi))


def _piece_extrema(ends: _Ends, a: torch.Tensor, p_lo: float, p_hi: float,
                   convex: bool | None, x0: torch.Tensor | None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sound (min, max) of r over [lo, hi] cap [p_lo, p_hi] and whether that piece is empty.

    convex: True / False for a piece of known curvature, None for a sliver evaluated by
    intervals (f enclosed over the whole fixed sliver [p_lo, p_hi], a constant).
    x0: approximate critical point (clamped into the piece here)."""
    kind, lo, hi = ends.kind, ends.lo, ends.hi
    pa = torch.clamp(lo, min=p_lo)
    pb = torch.clamp(hi, max=p_hi)
    empty = pa > pb
    pb = torch.where(empty, pa, pb)
    if convex is None:
        flo, fhi = _const_f(kind, p_lo, p_hi)
        f = Interval(torch.full_like(pa, flo), torch.full_like(pa, fhi))
        r = _minus_ax(f, a, pa, pb)
        return r.lo, r.hi, empty
    fa = ends.clamped(ends.f_lo, lo < p_lo, p_lo)
    fb = ends.clamped(ends.f_hi, hi > p_hi, p_hi)
    ra = _minus_ax(fa, a, pa, pa)
    rb = _minus_ax(fb, a, pb, pb)  # (empty pieces: any value, `_combine` drops them)
    x0 = torch.minimum(torch.maximum(x0, pa), pb)
    r0, dr0 = _residual(kind, x0, a)
    da = Interval(down(pa - x0), up(pa - x0))
    db = Interval(down(pb - x0), up(pb - x0))
    ta, tb = imul(dr0, da), imul(dr0, db)
    if convex:
        rmax = torch.maximum(ra.hi, rb.hi)
        rmin = down(r0.lo + torch.minimum(ta.lo, tb.lo))
    else:
        rmin = torch.minimum(ra.lo, rb.lo)
        rmax = up(r0.hi + torch.maximum(ta.hi, tb.hi))
    return rmin, rmax, empty


def _piece_extrema_where(ends: _Ends, a: torch.Tensor, p_lo: float, p_hi: float,
                         convex: bool | None, x0: torch.Tensor | None
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`_piece_extrema` computed only on the elements whose [lo, hi] meets the piece (the
    others are empty: +inf / -inf, dropped by `_combine`); the same values where computed."""
    meet = (ends.hi >= p_lo) & (ends.lo <= p_hi)
    inf = float("inf")
    rmin = torch.full_like(ends.lo, inf)
    rmax = torch.full_like(ends.lo, -inf)
    empty = ~meet
    if not bool(meet.any()):
        return rmin, rmax, empty
    if bool(meet.all()):
        return _piece_extrema(ends, a, p_lo, p_hi, convex, x0)
    mn, mx, em = _piece_extrema(ends.restrict(meet), a[meet], p_lo, p_hi, convex,
                                None if x0 is None else x0[meet])
    rmin[meet] = torch.where(em, torch.full_like(mn, inf), mn)
    rmax[meet] = torch.where(em, torch.full_like(mx, -inf), mx)
    return rmin, rmax, empty


def _combine(parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
             ) -> tuple[torch.Tensor, torch.Tensor]:
    inf = float("inf")
    rmin = rmax = None
    for pmin, pmax, empty in parts:
        pmin = torch.where(empty, torch.full_like(pmin, inf), pmin)
        pmax = torch.where(empty, torch.full_like(pmax, -inf), pmax)
        rmin = pmin if rmin is None else torch.minimum(rmin, pmin)
        rmax = pmax if rmax is None else torch.maximum(rmax, pmax)
    return rmin, rmax


def _chord_slope(f_lo: torch.Tensor, f_hi: torch.Tensor, df_mid: torch.Tensor,
                 lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    w = hi - lo
    thin = w <= 1e-7 * (1.0 + lo.abs())
    chord = (f_hi - f_lo) / torch.where(thin, torch.ones_like(w), w)
    return torch.where(thin, df_mid, chord)


def relax_tanh(lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
    """Parallel lines a x + b_lo <= tanh(x) <= a x + b_hi on [lo, hi], a the chord slope."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    mid = 0.5 * (lo + hi)
    a = _chord_slope(torch.tanh(lo), torch.tanh(hi), 1.0 - torch.tanh(mid) ** 2, lo, hi)
    a = torch.nan_to_num(a, nan=0.0).clamp(0.0, 1.0)
    # critical points of r: tanh'(x) = a  <=>  |x| = atanh(sqrt(1 - a))
    xc = torch.atanh(torch.sqrt((1.0 - a).clamp(0.0, 1.0)).clamp(max=1.0 - 1e-16))
    ends = _Ends("tanh", lo, hi)
    parts = [_piece_extrema_where(ends, a, -inf_(), 0.0, True, -xc),
             _piece_extrema_where(ends, a, 0.0, inf_(), False, xc)]
    rmin, rmax = _combine(parts)
    return LinearBounds(a, rmin, a, rmax)


def inf_() -> float:
    return float("inf")


def _dtanh_slope(x: torch.Tensor) -> torch.Tensor:
    t = torch.tanh(x)
    return -2.0 * t * (1.0 - t * t)


def _dtanh_crit(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points where tanh''(x) = a on each piece of known curvature: (left convex piece x <=
    -c, concave piece |x| <= c, right convex piece x >= c), in closed form. With T = tanh x,
    tanh'' = -2 T (1 - T^2) = a is the cubic T^3 - T - a/2 = 0, whose three real roots (|a| <=
    4 / (3 sqrt 3), the largest |tanh''|) are T_k = (2 / sqrt 3) cos(phi - 2 pi k / 3), phi =
    arccos(3 sqrt(3) a / 4) / 3: k = 0 the largest (T >= 1/sqrt 3), k = 1 the middle one, k = 2
    the smallest. A root outside (-1, 1) means no critical point on that piece (r' keeps
    its sign there): its x comes out at +-30 and `_piece_extrema` clamps it to the end the
    bisection it replaces would have reached. Float only: x0 affects tightness, never
    soundness (the tangent bound holds at any x0 of the piece)."""
    k = 3.0 * math.sqrt(3.0) / 4.0
    phi = torch.arccos((a * k).clamp(-1.0, 1.0)) / 3.0
    s = 2.0 / math.sqrt(3.0)

    def x_of(t: torch.Tensor) -> torch.Tensor:
        return torch.atanh(t.clamp(-1.0 + 1e-16, 1.0 - 1e-16)).clamp(-30.0, 30.0)

    third = 2.0 * math.pi / 3.0
    return (x_of(s * torch.cos(phi - 2.0 * third)), x_of(s * torch.cos(phi - third)),
            x_of(s * torch.cos(phi)))


def relax_dtanh(lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
    """Parallel lines a x + b_lo <= tanh'(x) <= a x + b_hi on [lo, hi], a the chord slope."""
    lo = lo.to(torch.float64)
    hi = hi.to(torch.float64)
    mid = 0.5 * (lo + hi)

    def s(x: torch.Tensor) -> torch.Tensor:
        t = torch.tanh(x)
        return 1.0 - t * t

    a = _chord_slope(s(lo), s(hi), _dtanh_slope(mid), lo, hi)
    a = torch.nan_to_num(a, nan=0.0)
    c_in, c_out = _C_D1 - _GAP, _C_D1 + _GAP
    x_left, x_mid, x_right = _dtanh_crit(a)
    ends = _Ends("dtanh", lo, hi)
    parts = [
        # convex (-inf, -c_out]: tanh'' increasing there
        _piece_extrema_where(ends, a, -inf_(), -c_out, True, x_left),
        # concave [-c_in, c_in]: tanh'' decreasing
        _piece_extrema_where(ends, a, -c_in, c_in, False, x_mid),
        # convex [c_out, inf): tanh'' increasing
        _piece_extrema_where(ends, a, c_out, inf_(), True, x_right),
        # the two slivers around +-c: tanh' enclosed over the whole sliver (a constant)
        _piece_extrema_where(ends, a, -c_out, -c_in, None, None),
        _piece_extrema_where(ends, a, c_in, c_out, None, None),
    ]
    rmin, rmax = _combine(parts)
    return LinearBounds(a, rmin, a, rmax)


def relax_value(act: Activation, lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
    """Parallel lines a x + b_lo <= f(x) <= a x + b_hi on [lo, hi] for the activation f."""
    return relax_tanh(lo, hi) if act.name == "tanh" else act.relax(lo, hi)


def relax_slope(act: Activation, lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
    """Parallel lines a x + b_lo <= f'(x) <= a x + b_hi on [lo, hi] for the activation f."""
    return relax_dtanh(lo, hi) if act.name == "tanh" else act.relax_d1(lo, hi)


@dataclass
class BilinearBounds:
    """s t >= as s + at t + bl and s t <= as s + at t + bu on [sl, su] x [tl, tu]."""

    slope_s: torch.Tensor
    slope_t: torch.Tensor
    lower_icpt: torch.Tensor
    upper_icpt: torch.Tensor


def mccormick(s: Interval, t: Interval) -> BilinearBounds:
    """Averaged McCormick planes for the product s * t (see the module docstring)."""
    sc = 0.5 * (s.lo + s.hi)
    tc = 0.5 * (t.lo + t.hi)
    if torch.equal(t.lo, t.hi):  # a point t (the first layer's tangent W0): tc = t exactly,
        q = sc * tc  # so s t - tc s - sc t = -sc t, one product within one ulp
        return BilinearBounds(tc, sc, -up(q), -down(q))
    # s t - tc s - sc t >= -(sl tl + su tu)/2 holds for the exact midpoints; for the float
    # sc, tc use the exact identity with the four corner values (bilinear => extremes at corners)
    corners = [(s.lo, t.lo), (s.lo, t.hi), (s.hi, t.lo), (s.hi, t.hi)]
    vals_lo, vals_hi = [], []
    for sv, tv in corners:
        # g(s, t) = s t - tc s - sc t is bilinear: its min / max over the box is at a corner;
        # each product of two floats is within one ulp of its rounded value
        p, q1, q2 = sv * tv, tc * sv, sc * tv
        vals_lo.append(down(down(down(p) - up(q1)) - up(q2)))
        vals_hi.append(up(up(up(p) - down(q1)) - down(q2)))
    bl = torch.minimum(torch.minimum(vals_lo[0], vals_lo[1]), torch.minimum(vals_lo[2], vals_lo[3]))
    bu = torch.maximum(torch.maximum(vals_hi[0], vals_hi[1]), torch.maximum(vals_hi[2], vals_hi[3]))
    return BilinearBounds(tc, sc, bl, bu)


__all__ = ["LinearBounds", "BilinearBounds", "relax_tanh", "relax_dtanh", "relax_value",
           "relax_slope", "mccormick"]
