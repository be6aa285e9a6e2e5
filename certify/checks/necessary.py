"""Pre-flight necessary condition, independent of the network (METHOD §3.5).

If k is C^1 and k(x, h(x)) = 0 on X, then on the output manifold y = h(xhat) and for every v
in ker dh(xhat), v^T D v = v^T (He{P Jf} + 2 lam P) v: no k in it. So

    q(xhat) = lam_max(Z^T (He{P Jf(xhat)} + 2 lam P) Z),   Z an orthonormal basis of ker dh,

must be <= 0 on {xhat in X : h(xhat) in Y} for ANY gain to pass MPDI and BC together. A
single point with q > 0 proves that no gain can (VIOLATED, with the witness); PROVED needs a
sound upper bound <= 0 (vertex enclosures of Jf on sub-boxes, then the interval prover).
Also reported: the rate cap for gains with exact BC and, for linear h where some q > 0 was
found, the residual eps_bar that any gain satisfying the MPDI everywhere must pay (chords
along ker C).

This module is the check: it runs the pieces and says what the result means. The quantities,
the search on the manifold and the sound bound are in `certify.design.manifold`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from certify.arith.text import lower_text, upper_text
from certify.checks.base import Check, Context
from certify.design.manifold import (
    gain_free_D,
    manifold_grid,
    on_manifold,
    q_values,
    rate_values,
    residual_price,
    search_manifold,
    vertex_upper_bound,
)
from certify.design.metric import kernel_basis, output_matrix
from certify.presentation import Presentation, Quantity
from certify.progress import NullProgress, Progress
from certify.results import NecessaryResult, Status
from certify.search.witness import is_witness, manifold_witness_lower
from certify.settings import VerifySettings
from certify.spec.system import System, validate_metric

_F64 = torch.float64
_NULL_PROGRESS = NullProgress()

#: the result's message and explanation when every state is measured (ker dh = {0})
VACUOUS = ("vacuous: all states are measured (dh has full column rank), so ker dh = {0} and "
           "the condition constrains no gain")
VACUOUS_EXPLANATION = ("The output determines every direction of the state, so the boundary "
                       "condition puts no constraint on the contraction condition: this "
                       "pre-flight cannot fail (there is no q to bound).")


def _fmt(v: list[float] | np.ndarray | torch.Tensor) -> str:
    return "(" + ", ".join(f"{float(a):.4g}" for a in v) + ")"


def check_necessary(system: System, P: np.ndarray | list | None, lam: float,
                    settings: VerifySettings | None = None, *,
                    progress: Progress = _NULL_PROGRESS,
                    grid_points: int = 200_000) -> NecessaryResult:
    """Network-independent pre-flight (METHOD §3.5) for metric P and rate lam.

    VIOLATED when some point of {xhat in X : h(xhat) in Y} has q > 0 (witness xhat and
    y = h(xhat), re-evaluated in float64); PROVED when a sound upper bound is <= 0; else
    UNKNOWN. Works for any n and p (nonlinear h: sampled side and rate cap only, unless the
    prover can bound it). `explanation` says in words what it means for the user.
    """
    t0 = time.perf_counter()
    settings = settings or VerifySettings()
    Pn = validate_metric(system.P if P is None else P, system.n, "necessary condition")
    if not (isinstance(lam, (int, float)) and math.isfinite(lam) and lam > 0):
        raise ValueError(f"lam must be a finite number > 0; got {lam!r}")
    Pt = torch.as_tensor(Pn, dtype=_F64)
    task = "necessary condition"
    progress.start(task, total=4)
    linear = system.h_is_linear
    C = output_matrix(system) if linear else None
    Zn = kernel_basis(C) if linear else None
    if linear and Zn.shape[1] == 0:
        progress.finish(task)
        return NecessaryResult(
            Status.PROVED, VACUOUS, -math.inf, -math.inf, None, None, None, None,
            explanation=VACUOUS_EXPLANATION, seconds=time.perf_counter() - t0)
    Z = torch.as_tensor(Zn, dtype=_F64) if linear else None
    x = manifold_grid(system, min(grid_points, settings.grid_points))
    x = x[on_manifold(system, x)]
    if not linear and system.p >= system.n and len(x):
        progress.finish(task)
        return _sampled_vacuous(system, Pt, lam, x, t0)
    if len(x) == 0:
        progress.finish(task)
        return NecessaryResult(Status.PROVED, "no point of X has h(x) in Y: the condition is "
                               "vacuous", -math.inf, -math.inf, None, None, None, None,
                               explanation="No state in X produces an output in Y, so there "
                               "is nothing to check.", seconds=time.perf_counter() - t0)
    fq = lambda z: q_values(system, Pt, lam, z, Z)  # noqa: E731
    with torch.no_grad():
        qg = fq(x)
    q_max, xw = search_manifold(system, fq, x, qg, starts=16, seed=settings.seed)
    progress.update(task)
    with torch.no_grad():  # the witness, re-evaluated alone in float64
        q_w = float(fq(xw[None])[0])
        y_w = system.h(xw[None])[0]
    q_max = q_w if math.isfinite(q_w) else q_max
    # rate cap: min over the manifold of the pointwise largest rate
    fr = lambda z: -rate_values(system, Pt, z, Z)  # noqa: E731
    with torch.no_grad():
        rg = fr(x)
    if linear:
        neg_cap, _ = search_manifold(system, fr, x, rg, starts=8, seed=settings.seed + 1)
    else:
        rg = torch.where(torch.isfinite(rg), rg, torch.full_like(rg, -math.inf))
        neg_cap = float(rg.max())
    rate_cap = 0.0 - neg_cap if math.isfinite(neg_cap) else None
    progress.update(task)
    price, chord = None, None
    if linear and q_max > 0:  # the price of a violation: none to pay where q <= 0 throughout
        dirs = [Z[:, j] for j in range(Z.shape[1])]
        with torch.no_grad():
            S_w = Z.T @ gain_free_D(system, Pt, lam, xw[None])[0] @ Z
            _, U = torch.linalg.eigh(S_w)
        dirs.append(Z @ U[:, -1])
        sel = torch.linspace(0, len(x) - 1, min(len(x), 2000)).long()
        with torch.no_grad():
            price, chord = residual_price(system, Pt, lam, torch.stack(dirs), x[sel])
    progress.update(task)
    upper: float | None = None
    q_sound = manifold_witness_lower(system, Pn, lam, xw) if q_max > 0 else None
    if is_witness(q_sound):
        status = Status.VIOLATED
        msg = (f"q = {q_max:.6g} > 0 at xhat = {_fmt(xw)}, y = {_fmt(y_w)} (sound lower bound "
               f"{lower_text(q_sound)}): no C^1 gain meets the MPDI and the boundary condition "
               "together with this P and lam")
    else:
        upper = vertex_upper_bound(system, Pn, lam)
        if upper is None or upper > 0:
            try:
                from certify.prove.side import bound_manifold_quantity
            except ImportError:  # pragma: no cover - the prover is part of the package
                bound_manifold_quantity = None
            if bound_manifold_quantity is not None:
                up2, _ = bound_manifold_quantity(system, Pn, lam)  # a budget of boxes
                if up2 is not None and (upper is None or up2 < upper):
                    upper = up2
        if upper is not None and upper <= 0:
            status = Status.PROVED
            msg = (f"q <= {upper_text(upper, 4)} on all of {{xhat in X : h(xhat) in Y}} "
                   "(sound bound); "
                   f"largest value found {q_max:.4g}")
        elif q_max > 0:
            status = Status.UNKNOWN
            msg = (f"near-tie: q evaluates to {q_max:.4g} > 0 at xhat = {_fmt(xw)} in float64, "
                   "but no sound lower bound > 0 there (within rounding error of 0) and no "
                   f"sound bound <= 0 (best {upper if upper is not None else 'none'})")
        else:
            status = Status.UNKNOWN
            msg = (f"largest q found {q_max:.4g} <= 0, but no sound bound <= 0 "
                   f"(best {upper if upper is not None else 'none'}) within the manifold "
                   "bound's box budget")
    progress.update(task)
    progress.finish(task, msg)
    expl = _explain(status, Pn, lam, q_max, xw, y_w, rate_cap, price, upper, system)
    return NecessaryResult(
        status=status, message=msg, q_max=float(q_max),
        q_upper=None if upper is None else float(upper),
        witness=xw.tolist(), witness_y=y_w.tolist(),
        rate_cap=None if rate_cap is None else float(rate_cap),
        residual_price=None if price is None else float(price),
        explanation=expl, seconds=time.perf_counter() - t0,
    )


def _sampled_vacuous(system: System, P: torch.Tensor, lam: float, x: torch.Tensor,
                     t0: float) -> NecessaryResult:
    """Nonlinear h with p >= n: ker dh = {0} wherever dh has full column rank, and there the
    condition is vacuous; that rank is only sampled here (the grid x on the manifold), so the
    answer is UNKNOWN, naming a point where the rank drops if the grid has one."""
    with torch.no_grad():
        q = q_values(system, P, lam, x, None)
    bad = torch.isnan(q)
    if bool(bad.any()):
        xb = x[int(torch.nonzero(bad)[0])]
        msg = (f"dh loses rank at xhat = {_fmt(xb)}: the kernel condition is not vacuous there "
               "and is not evaluated for a nonlinear h with p >= n")
    else:
        msg = (f"dh has full column rank at all {len(x)} sampled points: the condition is "
               "vacuous there (all states seen by the output), but the rank is not proved "
               "everywhere")
    return NecessaryResult(Status.UNKNOWN, msg, -math.inf, None, None, None, None, None,
                           explanation="With every state direction measured the boundary "
                           "condition constrains no gain; " + msg + ".",
                           seconds=time.perf_counter() - t0)


def _explain(status: Status, P: np.ndarray, lam: float, q_max: float, xw: torch.Tensor,
             yw: torch.Tensor, rate_cap: float | None, price: float | None,
             upper: float | None, system: System) -> str:
    """One paragraph, in words, of what the pre-flight means for the user."""
    Pdesc = "P = I" if np.allclose(P, np.eye(len(P))) else "the given metric P"
    cap = ""
    if rate_cap is not None:
        cap = (f" Any gain that satisfies the boundary condition exactly can contract at rate "
               f"at most {rate_cap:.4g}" + (" (that is, not at all)" if rate_cap <= 0 else "")
               + ".")
    if status is Status.VIOLATED:
        txt = (f"With {Pdesc} and lam = {lam:g}, no continuously differentiable gain can "
               f"satisfy both the contraction condition D <= 0 and the boundary condition "
               f"k(x, h(x)) = 0 on this box, whatever the network. At xhat = {_fmt(xw)} "
               f"(y = {_fmt(yw)}) the output cannot see some state direction; along it D <= 0 "
               f"reduces to a quantity that does not involve the gain at all, and that "
               f"quantity is {q_max:.4g} > 0.{cap}")
        if price is not None and price > 0:
            diam = float(np.linalg.norm(system.X[:, 1] - system.X[:, 0]))
            txt += (f" A gain that does satisfy D <= 0 everywhere must break the boundary "
                    f"condition by eps_bar >= {price:.4g}, which adds at least "
                    f"{price / (2 * lam):.4g} to the guaranteed error bound (the box diameter "
                    f"is {diam:.4g}), so such a certificate would say little.")
        txt += (" Remedies: search a metric P that passes this test (certify check --metric), "
                "lower lam below the rate cap, or use a box that avoids the witness.")
        return txt
    if status is Status.PROVED:
        return (f"With {Pdesc} and lam = {lam:g} the network-independent obstruction is absent: "
                f"on every state whose output lies in Y, the directions the output cannot see "
                f"already contract (sound bound {upper_text(upper, 4)} <= 0). Whether the "
                "trained gain "
                f"meets the contraction condition is the MPDI check's job.{cap}")
    return (f"No point violating the necessary condition was found (largest value "
            f"{q_max:.4g}), but it could not be proved everywhere within the budget; the MPDI "
            f"check decides for the network itself.{cap}")


# ----------------------------------------------------------------------------- check protocol

class NecessaryCheck(Check):
    """The network-independent pre-flight: q <= 0 on the output manifold."""

    name = "necessary"
    title = "Pre-flight necessary condition"
    result_type = NecessaryResult
    reads = ("grid_points", "seed")

    def run(self, context: Context) -> NecessaryResult:
        p = context.problem
        return check_necessary(p.system, p.P, p.lam, context.settings,
                               progress=context.progress)

    def present(self, r: NecessaryResult, certificate: Any) -> Presentation:
        # q = -inf: no direction hidden from the output, so there is no q (not a number to show)
        none = "none: every state is measured"
        q_max = None if r.q_max == -math.inf else r.q_max
        q_up = None if r.q_upper == -math.inf else r.q_upper
        no_bound = none if r.q_upper == -math.inf else "not bounded"
        return Presentation(
            sampled=Quantity("max q found", q_max, none, signed=True, bound="lower"),
            proved=Quantity("q \u2264 (sound bound)", q_up, no_bound, signed=True,
                            bound="upper"),
            setting=(Quantity("\u03bb =", certificate.lam),
                     Quantity("P =", certificate.P, sig=3)),
            numbers=(Quantity("q_max", q_max, none, sig=6, signed=True, bound="lower"),
                     Quantity("q_upper", q_up, no_bound, sig=6, signed=True, bound="upper"),
                     Quantity("witness", r.witness),
                     Quantity("rate cap", r.rate_cap, sig=6, bound="upper"),
                     Quantity("residual price", r.residual_price, sig=6, bound="lower")),
            facts=(Quantity("Status", r.status.value),
                   Quantity("max q found", q_max, none, sig=6, signed=True, bound="lower"),
                   Quantity("Sound bound q \u2264", q_up, no_bound, sig=6,
                            signed=True, bound="upper"),
                   Quantity("Witness x\u0302", r.witness),
                   Quantity("Witness y = h(x\u0302)", r.witness_y),
                   Quantity("Rate cap (any gain with exact BC)", r.rate_cap, "not computed",
                            sig=5, signed=True, bound="upper"),
                   Quantity("Price in residual (\u03b5\u0304 \u2265)", r.residual_price,
                            "not applicable", sig=5, bound="lower")))


CHECK = NecessaryCheck()
