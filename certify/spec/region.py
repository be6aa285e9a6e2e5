"""A plant region R inside the box X, to be proved forward invariant: its kinds and checks.

Three kinds, each a closed set inside X:

- ``polygon`` (n = 2): a simple polygon, its vertices in order (stored counter-clockwise);
- ``box``: a box [lo_i, hi_i] inside X;
- ``sublevel``: ``R = {x in X : V(x) <= level}`` for an expression V in the state names
  (parsed by the spec's whitelist parser, defined and smooth on X), with V > level on the
  boundary of X, so that R does not touch it.

`parse_region` reads the spec's `[invariance]` table and refuses (one `SpecError` line) a
region that is degenerate or not inside X: a polygon with fewer than 3 vertices, a repeated
vertex, no area or crossing edges; a vertex or box outside X; a sublevel set that is empty at
the points tried or reaches the boundary of X at one of them. Whether R is forward
invariant is for the prover (`certify.prove.invariance`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy

from certify.errors import SpecError

KINDS = ("polygon", "box", "sublevel")
#: the keys of the spec's [invariance] table
KEYS = frozenset({"polygon", "box", "V", "level"})
#: points per axis at which a sublevel set's boundary condition and emptiness are tried when
#: the spec is read (the prover proves the boundary condition; this only refuses bad input)
SAMPLE_POINTS = 33


@dataclass(frozen=True, eq=False)
class Region:
    """A region R of the plant's state space (see the module docstring).

    `vertices` [m, 2] (polygon, counter-clockwise), `box` [n, 2] (box), or `V_text` and
    `level` (sublevel; `V` the parsed expression with every float constant an exact
    rational, so that its derivatives are exact). `origin`: "spec" (given by the user) or
    "found" (constructed by certify from a simulation of the plant)."""

    kind: str
    vertices: np.ndarray | None = None
    box: np.ndarray | None = None
    V_text: str = ""
    level: float | None = None
    V: Any = None
    symbols: tuple = ()
    origin: str = "spec"

    @property
    def n(self) -> int:
        if self.kind == "polygon":
            return 2
        if self.kind == "box":
            return int(self.box.shape[0])  # type: ignore[union-attr]
        return len(self.symbols)

    def bounding_box(self) -> np.ndarray | None:
        """The smallest box holding R [n, 2] for a polygon or a box (exact: vertex
        coordinates); None for a sublevel set (the prover bounds it)."""
        if self.kind == "polygon":
            v = self.vertices
            return np.stack([v.min(0), v.max(0)], 1)  # type: ignore[union-attr]
        if self.kind == "box":
            return np.array(self.box, dtype=np.float64)
        return None

    def describe(self) -> str:
        """R in words: 'a polygon of 48 vertices', 'the box [..] x [..]', '{V <= c}'."""
        if self.kind == "polygon":
            return f"a polygon of {len(self.vertices)} vertices"  # type: ignore[arg-type]
        if self.kind == "box":
            return "the box " + " x ".join(f"[{lo:.4g}, {hi:.4g}]" for lo, hi in self.box)
        return f"{{x in X : {self.V_text} <= {self.level:.6g}}}"

    def to_dict(self) -> dict[str, Any]:
        """Plain data for a result: kind, origin, R in words (text) and the numbers that
        define it."""
        out: dict[str, Any] = {"kind": self.kind, "origin": self.origin,
                               "text": self.describe()}
        if self.kind == "polygon":
            out["vertices"] = np.asarray(self.vertices).tolist()
        elif self.kind == "box":
            out["box"] = np.asarray(self.box).tolist()
        else:
            out["V"], out["level"] = self.V_text, self.level
        return out


def exact_rationals(expr: sympy.Expr) -> sympy.Expr:
    """`expr` with every float constant replaced by the rational it stands for exactly (a
    double is a dyadic rational), so that sympy's derivatives of it are exact."""
    floats = expr.atoms(sympy.Float)
    return expr.xreplace({a: sympy.Rational(a) for a in floats}) if floats else expr


def _numbers(value: Any, shape_words: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SpecError(f"{where} must be {shape_words}") from None
    if not np.all(np.isfinite(arr)):
        raise SpecError(f"{where} has a non-finite number")
    return arr


def _outside_x(points: np.ndarray, X: np.ndarray) -> int | None:
    bad = np.nonzero(((points < X[:, 0]) | (points > X[:, 1])).any(1))[0]
    return int(bad[0]) if bad.size else None


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _segments_meet(p: np.ndarray, q: np.ndarray, r: np.ndarray, s: np.ndarray,
                   tol: float) -> bool:
    """Whether segments pq and rs intersect or come within `tol` of each other (errs
    towards yes)."""
    d1, d2 = _cross(p, q, r), _cross(p, q, s)
    d3, d4 = _cross(r, s, p), _cross(r, s, q)
    if ((d1 > tol and d2 < -tol) or (d1 < -tol and d2 > tol)) and \
            ((d3 > tol and d4 < -tol) or (d3 < -tol and d4 > tol)):
        return True

    def dist(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:  # point c to segment ab
        ab = b - a
        t = float(np.clip(np.dot(c - a, ab) / max(float(np.dot(ab, ab)), 1e-300), 0.0, 1.0))
        return float(np.linalg.norm(a + t * ab - c))

    gap = min(dist(p, q, r), dist(p, q, s), dist(r, s, p), dist(r, s, q))
    return gap <= math.sqrt(tol)


def check_polygon(vertices: Any, X: np.ndarray, where: str) -> np.ndarray:
    """A polygon's vertices [m, 2] as given, counter-clockwise; refuse (one line) fewer than 3
    vertices, a vertex outside X, a repeated vertex, no area or edges that meet other than
    at a shared vertex."""
    v = _numbers(vertices, "a list of [x1, x2] vertices", where)
    if v.ndim != 2 or v.shape[1] != 2:
        raise SpecError(f"{where} must be a list of [x1, x2] vertices; got shape "
                        f"{list(v.shape)}")
    m = v.shape[0]
    if m < 3:
        raise SpecError(f"{where} is degenerate: it has {m} vertices (a polygon needs at "
                        "least 3)")
    bad = _outside_x(v, X)
    if bad is not None:
        raise SpecError(f"{where} is not inside X: vertex {bad} = ({v[bad, 0]:g}, "
                        f"{v[bad, 1]:g}) lies outside X")
    scale = float(np.abs(v).max()) + float((v.max(0) - v.min(0)).max())
    tol = (1e-9 * scale) ** 2
    edges = np.roll(v, -1, 0) - v
    short = np.nonzero(np.linalg.norm(edges, axis=1) <= 1e-9 * scale)[0]
    if short.size:
        k = int(short[0])
        raise SpecError(f"{where} is degenerate: vertices {k} and {(k + 1) % m} coincide")
    area = 0.5 * float(np.sum(v[:, 0] * np.roll(v, -1, 0)[:, 1]
                              - np.roll(v, -1, 0)[:, 0] * v[:, 1]))
    if abs(area) <= 1e-9 * scale * scale:
        raise SpecError(f"{where} is degenerate: it encloses no area")
    for i in range(m):
        # an edge folding back on the next one
        nxt = (i + 1) % m
        if abs(_cross(v[i], v[nxt], v[(i + 2) % m])) <= tol and \
                float(np.dot(edges[i], edges[nxt])) < 0:
            raise SpecError(f"{where} is degenerate: the edges at vertex {nxt} fold back "
                            "on each other")
        for j in range(i + 2, m):
            if i == 0 and j == m - 1:
                continue  # adjacent through vertex 0
            if _segments_meet(v[i], v[nxt], v[j], v[(j + 1) % m], tol):
                raise SpecError(f"{where} is not a simple polygon: edge {i} (vertices {i}, "
                                f"{nxt}) meets edge {j} (vertices {j}, {(j + 1) % m})")
    return v if area > 0 else v[::-1].copy()


def check_box(box: Any, X: np.ndarray, where: str) -> np.ndarray:
    """A box [n, 2] inside X; refuse (one line) a malformed, empty or outside one."""
    b = _numbers(box, "a list of [lo, hi] rows", where)
    n = X.shape[0]
    if b.shape != (n, 2):
        raise SpecError(f"{where} must have {n} rows of [lo, hi]; got shape {list(b.shape)}")
    for i in range(n):
        if not b[i, 0] < b[i, 1]:
            raise SpecError(f"{where} row {i} is empty or inverted ([{b[i, 0]:g}, "
                            f"{b[i, 1]:g}]; need lo < hi)")
        if b[i, 0] < X[i, 0] or b[i, 1] > X[i, 1]:
            raise SpecError(f"{where} is not inside X: row {i} [{b[i, 0]:g}, {b[i, 1]:g}] "
                            f"leaves [{X[i, 0]:g}, {X[i, 1]:g}]")
    return b


def sublevel_samples(V: sympy.Expr, symbols: tuple, X: np.ndarray, level: float, where: str,
                     text: str) -> None:
    """Refuse (one line) a sublevel set {x in X : V <= level} that is empty at a grid of
    points of X or reaches X's boundary at one of them (float evaluation: a screening of
    the input; the prover proves V > level on the boundary)."""
    n = X.shape[0]
    k = max(3, int(round(SAMPLE_POINTS ** (2.0 / max(n, 2)))))
    axes = [np.linspace(lo, hi, k) for lo, hi in X]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, n)
    from certify.spec.expr import compile_numpy_rows

    fn = compile_numpy_rows([V], symbols, "the region's V")
    with np.errstate(all="ignore"):
        vals = np.asarray(fn(grid), dtype=np.float64)[:, 0]
    on_edge = ((grid == X[:, 0]) | (grid == X[:, 1])).any(1)
    hit = np.nonzero(on_edge & (vals <= level))[0]
    if hit.size:
        x = ", ".join(f"{c:g}" for c in grid[hit[0]])
        raise SpecError(f"{where}: the region {{{text} <= {level:g}}} is not inside X: it "
                        f"reaches the boundary of X at ({x})")
    if not bool((vals <= level).any()):
        raise SpecError(f"{where}: the region {{{text} <= {level:g}}} is empty at every "
                        f"point tried in X ({len(grid)} points)")


def parse_region(table: Any, *, X: np.ndarray, states: list[str],
                 symbols: list[sympy.Symbol], where: str) -> Region | None:
    """The spec's [invariance] table as a `Region` (None without one); one `SpecError` line
    for anything else (see the module docstring)."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise SpecError(f"{where}: [invariance] must be a table")
    given = [k for k in ("polygon", "box", "V") if k in table]
    if len(given) != 1:
        raise SpecError(f"{where}: [invariance] needs exactly one of polygon, box or V "
                        f"(with level); got {', '.join(given) or 'none'}")
    if "level" in table and given != ["V"]:
        raise SpecError(f"{where}: [invariance] level goes with V only")
    place = f"{where}: [invariance]"
    if given == ["polygon"]:
        if len(states) != 2:
            raise SpecError(f"{place} polygon needs n = 2 states; this system has "
                            f"{len(states)} (use box or V)")
        return Region("polygon", vertices=check_polygon(table["polygon"], X,
                                                        f"{place} polygon"))
    if given == ["box"]:
        return Region("box", box=check_box(table["box"], X, f"{place} box"))
    text = table["V"]
    if not isinstance(text, str):
        raise SpecError(f"{place} V must be an expression string in the state names")
    if "level" not in table:
        raise SpecError(f"{place} V needs a level (the region is {{x in X : V(x) <= level}})")
    level = table["level"]
    if isinstance(level, bool) or not isinstance(level, (int, float)) or \
            not math.isfinite(float(level)):
        raise SpecError(f"{place} level must be a finite number; got {level!r}")
    from certify.spec.domain import check_domain
    from certify.spec.expr import parse_expression

    names = dict(zip(states, symbols))
    sources: dict[sympy.Expr, str] = {}
    parsed = parse_expression(text, names, f"{place} V", sources=sources)
    (checked,) = check_domain([parsed], [text], symbols, X, [f"{place} V"], sources)
    V = exact_rationals(checked)
    sublevel_samples(V, tuple(symbols), X, float(level), place, text)
    return Region("sublevel", V_text=text, level=float(level), V=V, symbols=tuple(symbols))


@functools.lru_cache(maxsize=64)
def _gradient(V: sympy.Expr, symbols: tuple) -> tuple[tuple[sympy.Expr, ...],
                                                      tuple[tuple[sympy.Expr, ...], ...]]:
    grad = tuple(sympy.diff(V, s) for s in symbols)
    hess = tuple(tuple(sympy.diff(g, s) for s in symbols) for g in grad)
    return grad, hess


def derivatives(region: Region) -> tuple[tuple[sympy.Expr, ...],
                                         tuple[tuple[sympy.Expr, ...], ...]]:
    """The gradient and Hessian of a sublevel region's V (exact: V has rational constants),
    cached."""
    return _gradient(region.V, region.symbols)
