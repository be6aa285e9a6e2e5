"""System specs: TOML -> a validated `System` with sympy, Jacobians and batched torch maps.

A spec names the states and outputs, gives `f` and `h` as expression strings (parsed as
written by `certify.spec.parse`, then checked to be defined and smooth on X by
`certify.spec.domain`),
the boxes X and Y, and the design settings. The
built-ins live in `certify/spec/builtin/*.toml`; users pass a path to their own file.
"""

from __future__ import annotations

import ast
import functools
import json
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sympy
import torch

from certify.errors import SettingsError, SpecError
from certify.spec import builtin
from certify.spec.domain import check_domain
from certify.spec.expr import CompiledRows, compile_numpy_rows, compile_torch_rows, parse_expression
from certify.spec.region import KEYS as region_keys
from certify.spec.region import Region, parse_region

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def builtin_names() -> list[str]:
    """Names of the systems shipped with the package."""
    return builtin.names()


def builtin_text(name: str) -> str:
    return builtin.text(name)


def _box(value: Any, dim: int, what: str, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SpecError(f"{where}: box {what} must be a list of [lo, hi] pairs") from None
    if arr.shape != (dim, 2):
        raise SpecError(f"{where}: box {what} must have {dim} rows of [lo, hi]; got shape "
                        f"{list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise SpecError(f"{where}: box {what} has a non-finite bound")
    bad = np.nonzero(arr[:, 0] >= arr[:, 1])[0]
    if bad.size:
        i = int(bad[0])
        raise SpecError(f"{where}: box {what} row {i} is empty or inverted "
                        f"([{arr[i, 0]:g}, {arr[i, 1]:g}]; need lo < hi)")
    return arr


def validate_metric(P: Any, n: int, where: str) -> np.ndarray:
    """Check that P is a symmetric positive definite n x n matrix; return it as float64."""
    try:
        arr = np.asarray(P, dtype=np.float64)
    except (TypeError, ValueError):
        raise SpecError(f"{where}: metric P must be an n x n matrix of numbers") from None
    if arr.shape != (n, n):
        raise SpecError(f"{where}: metric P must be {n}x{n}; got shape {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise SpecError(f"{where}: metric P has a non-finite entry")
    if not np.allclose(arr, arr.T, rtol=0, atol=1e-12 * max(1.0, np.abs(arr).max())):
        raise SpecError(f"{where}: metric P must be symmetric")
    arr = (arr + arr.T) / 2
    if np.linalg.eigvalsh(arr).min() <= 0:
        raise SpecError(f"{where}: metric P must be positive definite")
    return arr


#: the largest rate accepted: beyond it 2 lam P swamps Jf + dk/dx in float64 (their sum
#: rounds to 2 lam P) and its entries can overflow, so no check could say anything about k
MAX_LAM = 1e12


def validate_lam(lam: Any, where: str) -> float:
    """lam as a float: a finite number in (0, MAX_LAM] (else one `SpecError` line naming
    `where`). Every entry point that takes a rate from the user (`--lam`, a spec, a
    checkpoint) refuses the same values, so an infinite or absurd rate is bad input (exit 2),
    not an internal error (2 lam P overflowing in the SDP) or an inconclusive run."""
    if isinstance(lam, bool) or not isinstance(lam, (int, float)):  # not "2.5", not True
        raise SpecError(f"{where} must be a finite number > 0; got {lam!r}")
    v = float(lam)
    if not (np.isfinite(v) and v > 0):
        raise SpecError(f"{where} must be a finite number > 0; got {lam!r}")
    if v > MAX_LAM:
        raise SpecError(f"{where} must be at most {MAX_LAM:g} (a larger rate swamps the "
                        f"Jacobians in D in float64); got {lam!r}")
    return v


#: The keys a spec may hold, by table ("" is the top level; "training.paper" the table
#: [training.paper]). Any other key is refused, naming it, so that a misspelt key is an
#: error rather than a default silently used; docs/spec-format.md documents each one (a
#: test keeps the two the same).
SPEC_KEYS: dict[str, frozenset[str]] = {
    "": frozenset({"name", "description", "states", "outputs", "f", "h", "box", "design",
                   "training", "simulation", "invariance"}),
    "box": frozenset({"X", "Y"}),
    "design": frozenset({"lam", "P", "state_metric"}),
    "design.state_metric": frozenset({"kind", "format", "exponents", "coefficients"}),
    "training": frozenset({"paper"}),
    "training.paper": frozenset({"mu1", "mu2", "rho"}),
    "simulation": frozenset({"x0", "xhat0", "t_final"}),
    "invariance": region_keys,
}


def check_keys(data: dict[str, Any], where: str) -> None:
    """Refuse (one `SpecError` line) a table that is not a table and a key not in
    `SPEC_KEYS`."""
    for table, known in SPEC_KEYS.items():
        node: Any = data
        for part in table.split(".") if table else ():
            node = node.get(part) if isinstance(node, dict) else None
        if node is None:
            continue
        if not isinstance(node, dict):
            raise SpecError(f"{where}: [{table}] must be a table")
        unknown = sorted(set(node) - known)
        if unknown:
            place = f"[{table}]" if table else "the spec"
            raise SpecError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                            f"{', '.join(repr(k) for k in unknown)} in {place} (known: "
                            f"{', '.join(sorted(known))})")


def _state_metric(table: Any, where: str) -> dict[str, Any] | None:
    """The [design.state_metric] table as given (kind 'polynomial' by default); its
    exponents and coefficients are checked where the metric is built
    (`certify.model.metric.PolyMetric.from_dict`)."""
    if table is None:
        return None
    if "exponents" not in table or "coefficients" not in table:
        raise SpecError(f"{where}: [design.state_metric] needs exponents (one list of "
                        "powers per monomial) and coefficients (one n x n matrix per "
                        "monomial)")
    return {"kind": "polynomial", **table}


@dataclass(eq=False)
class System:
    """A validated system spec. Build with `System.from_text` or `load_system`."""

    name: str
    description: str
    states: list[str]
    outputs: list[str]
    f_text: list[str]
    h_text: list[str]
    X: np.ndarray  # [n, 2]
    Y: np.ndarray  # [p, 2]
    lam: float
    P: np.ndarray  # [n, n]
    training: dict[str, dict[str, Any]] = field(default_factory=dict)
    simulation: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    #: the plant region of the spec's [invariance] table (`certify.spec.region`), to be
    #: proved forward invariant; None: certify looks for one
    invariance: Region | None = None
    #: the spec's [design.state_metric] table (a metric that follows the state, the plain
    #: data of `certify.model.metric.PolyMetric`), read into a metric where a model is
    #: imported against this spec; None: no such metric
    state_metric: dict[str, Any] | None = None

    # ----- construction -------------------------------------------------------------
    @classmethod
    def from_text(cls, text: str, origin: str = "spec") -> System:
        """Parse and validate TOML spec text; errors name `origin` and the field."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SpecError(f"{origin}: not valid TOML ({exc})") from None
        where = origin
        check_keys(data, where)

        def need(key: str, kind: type | tuple[type, ...]) -> Any:
            if key not in data:
                raise SpecError(f"{where}: missing field '{key}'")
            if not isinstance(data[key], kind):
                raise SpecError(f"{where}: field '{key}' has the wrong type")
            return data[key]

        name = need("name", str)
        states = need("states", list)
        outputs = need("outputs", list)
        for what, names in (("states", states), ("outputs", outputs)):
            if not names:
                raise SpecError(f"{where}: '{what}' must not be empty")
            for s in names:
                if not isinstance(s, str) or not _IDENT.match(s):
                    raise SpecError(f"{where}: {what} entry {s!r} is not a valid name")
        if len(set(states) | set(outputs)) != len(states) + len(outputs):
            raise SpecError(f"{where}: state and output names must be distinct")
        f_text = need("f", list)
        h_text = need("h", list)
        if len(f_text) != len(states):
            raise SpecError(f"{where}: f has {len(f_text)} entries for {len(states)} states")
        if len(h_text) != len(outputs):
            raise SpecError(f"{where}: h has {len(h_text)} entries for {len(outputs)} outputs")
        box = data.get("box")
        if not isinstance(box, dict) or "X" not in box or "Y" not in box:
            raise SpecError(f"{where}: missing [box] table with X and Y")
        X = _box(box["X"], len(states), "X", where)
        Y = _box(box["Y"], len(outputs), "Y", where)
        design = data.get("design", {})
        lam = design.get("lam", 1.0)
        lam = validate_lam(lam, f"{where}: design lam")
        P = validate_metric(design.get("P", np.eye(len(states)).tolist()), len(states),
                            f"{where}: design")
        system = cls(
            name=name, description=str(data.get("description", "")), states=list(states),
            outputs=list(outputs), f_text=[str(e) for e in f_text],
            h_text=[str(e) for e in h_text], X=X, Y=Y, lam=float(lam), P=P,
            training=dict(data.get("training", {})), simulation=dict(data.get("simulation", {})),
            source=text, state_metric=_state_metric(design.get("state_metric"), where),
        )
        system._parse(where)
        system.invariance = parse_region(data.get("invariance"), X=X, states=list(states),
                                         symbols=system.symbols, where=where)
        return system

    def _parse(self, where: str) -> None:
        syms = {s: sympy.Symbol(s, real=True) for s in self.states}
        self.symbols = [syms[s] for s in self.states]
        labels = [f"{where}: f[{i}]" for i in range(len(self.f_text))] + \
            [f"{where}: h[{i}]" for i in range(len(self.h_text))]
        texts = self.f_text + self.h_text
        sources: dict[sympy.Expr, str] = {}
        parsed = [parse_expression(t, syms, w, sources=sources) for t, w in zip(texts, labels)]
        # every sub-expression defined and smooth on X (abs resolved to +-u): certify.spec.domain
        checked = check_domain(parsed, texts, self.symbols, self.X, labels, sources)
        self.f_expr, self.h_expr = checked[:self.n], checked[self.n:]
        x = sympy.Matrix(self.symbols)
        self.jf_expr = sympy.Matrix(self.f_expr).jacobian(x)  # n x n
        self.jh_expr = sympy.Matrix(self.h_expr).jacobian(x)  # p x n
        self._compiled: dict[str, CompiledRows] = {}

    # ----- sizes ------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.states)

    @property
    def p(self) -> int:
        return len(self.outputs)

    @functools.cached_property
    def jacobians_constant(self) -> bool:
        """True when df/dx and dh/dx are constant matrices (f and h affine in x)."""
        return self.h_is_linear and not any(e.free_symbols for e in self.jf_expr)

    @functools.cached_property
    def h_is_linear(self) -> bool:
        """True when h(x) = C x + d (then ker dh is constant)."""
        return all(sympy.diff(e, s) == 0 for e in self.jh_expr for s in self.symbols)

    # ----- batched point evaluation ------------------------------------------------------
    def _rows(self, key: str, numpy: bool = False) -> CompiledRows:
        """The generated evaluator of expression list `key` (built on first use); `numpy`:
        the NumPy form (`certify.spec.expr.compile_numpy_rows`)."""
        name = key + (":numpy" if numpy else "")
        fn = self._compiled.get(name)
        if fn is None:
            exprs = {"f": self.f_expr, "h": self.h_expr, "fh": [*self.f_expr, *self.h_expr],
                     "jf": list(self.jf_expr), "jh": list(self.jh_expr)}[key]
            compile_rows = compile_numpy_rows if numpy else compile_torch_rows
            fn = self._compiled[name] = compile_rows(exprs, self.symbols, f"{self.name} {key}")
        return fn

    def array_rows(self, key: str) -> Callable[[np.ndarray], np.ndarray]:
        """The NumPy evaluator of "f" or "fh" (= [f, h]) on float64 arrays [B, n]: the
        integrator's right-hand side (`certify.simulate.integrate`), where each call is a few rows
        and NumPy's per-call cost is a quarter of torch's. No shape check (the caller's
        shapes are fixed)."""
        if key not in ("f", "fh"):
            raise ValueError(f"array_rows evaluates 'f' or 'fh'; got {key!r}")
        return self._rows(key, numpy=True)

    def _eval(self, key: str, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 2 or x.shape[1] != self.n:
            raise ValueError(f"expected states of shape [batch, {self.n}]; got {list(x.shape)}")
        return self._rows(key)(x)

    def f(self, x: torch.Tensor) -> torch.Tensor:
        """f(x) for x of shape [B, n] -> [B, n]."""
        return self._eval("f", x)

    def h(self, x: torch.Tensor) -> torch.Tensor:
        """h(x) for x of shape [B, n] -> [B, p]."""
        return self._eval("h", x)

    def f_and_h(self, x: torch.Tensor) -> torch.Tensor:
        """[f(x), h(x)] for x [B, n] -> [B, n + p] in one call (the same values as `f` and
        `h`; shared sub-expressions computed once): the simulation's right-hand side."""
        return self._eval("fh", x)

    def jac_f(self, x: torch.Tensor) -> torch.Tensor:
        """Symbolic Jacobian df/dx at x [B, n] -> [B, n, n]."""
        return self._eval("jf", x).reshape(-1, self.n, self.n)

    def jac_h(self, x: torch.Tensor) -> torch.Tensor:
        """Symbolic Jacobian dh/dx at x [B, n] -> [B, p, n]."""
        return self._eval("jh", x).reshape(-1, self.p, self.n)

    # ----- presentation ------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Plain-data description for certificates and reports."""
        return {
            "name": self.name, "description": self.description, "states": self.states,
            "outputs": self.outputs, "f": self.f_text, "h": self.h_text,
            "X": self.X.tolist(), "Y": self.Y.tolist(), "lam": self.lam, "P": self.P.tolist(),
            "jacobian_f": [[str(e) for e in row] for row in self.jf_expr.tolist()],
        }


def load_system(name_or_path: str | Path) -> System:
    """A built-in system by name, or a spec file by path."""
    key = str(name_or_path)
    if key in builtin_names():
        return System.from_text(builtin_text(key), origin=f"built-in system {key}")
    path = Path(key)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise SpecError(f"spec file {key} not found")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise SpecError(f"spec {key}: cannot read ({exc})") from None
        return System.from_text(text, origin=f"spec {path.name}")
    raise SpecError(f"unknown system '{key}' (built-ins: {', '.join(builtin_names())}; "
                    "or give the path of a .toml spec)")


def parse_metric(text: str, n: int | None = None) -> tuple[tuple[float, ...], ...]:
    """'[[a,b],[b,c]]' -> a validated symmetric positive definite matrix (JSON or a Python
    literal; never evaluated as code)."""
    try:
        value: Any = json.loads(text)
    except (json.JSONDecodeError, TypeError):
        try:
            value = ast.literal_eval(str(text))
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            raise SettingsError(f"--metric must be a matrix like [[1, 0], [0, 1]]; got "
                                f"{text!r}") from None
    ok = isinstance(value, (list, tuple)) and len(value) > 0 and all(
        isinstance(row, (list, tuple)) and len(row) == len(value)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
        for row in value)
    if not ok:
        raise SettingsError(f"--metric must be a square matrix of numbers like "
                            f"[[1, 0], [0, 1]]; got {text!r}")
    arr = np.asarray(value, dtype=np.float64)
    if n is not None and arr.shape != (n, n):
        raise SettingsError(f"--metric must be {n}x{n} for this system; got "
                            f"{arr.shape[0]}x{arr.shape[1]}")
    if not np.all(np.isfinite(arr)):
        raise SettingsError(f"--metric has a non-finite entry; got {text!r}")
    if not np.allclose(arr, arr.T, rtol=0, atol=1e-12 * max(1.0, float(np.abs(arr).max()))):
        raise SettingsError(f"--metric must be symmetric; got {text!r}")
    if float(np.linalg.eigvalsh((arr + arr.T) / 2).min()) <= 0:
        raise SettingsError(f"--metric must be positive definite; got {text!r}")
    return tuple(tuple(float(v) for v in row) for row in arr)
