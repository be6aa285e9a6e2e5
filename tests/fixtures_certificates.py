"""Hand-built, realistic `Certificate` objects for the report tests (no verification run).

Three shapes, each with figure arrays as `certify/verify.py` would produce them
(see the figure data contract in the certificate schema):

- `certified_certificate()`: a metric-P design on an enlarged VdP box, everything proved;
- `violated_vdp_certificate()`: the paper preset of VdP (P = I, lam = 2.5): MPDI VIOLATED
  with lam_max(D) up to +7.7, necessary condition failing at x1 = 0 with q = 6, lam_cert
  negative so no error bound, and the source's simulation leaving X;
- `inconclusive_certificate()`: reverse Duffing, proof budget spent with upper bound +0.013.

The numbers are synthetic but consistent with each other (sampled side below proved side,
bounds computed with the formulas of METHOD.md section 3); trajectories are integrated.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from certify.certificate import Certificate
from certify.results import (
    BoundResult,
    BoundsResult,
    Counterexample,
    LipschitzResult,
    MetricResult,
    MpdiResult,
    NecessaryResult,
    ProofStats,
    RateResult,
    ResidualResult,
    SimulationResult,
    SimulationRun,
    Status,
    decide_verdict,
    to_jsonable,
)
from certify.settings import VerifySettings

VERSIONS = {"certify": "0.1.0", "torch": "2.13.0", "numpy": "2.1.3", "scipy": "1.14.1",
            "sympy": "1.13.3", "cvxpy": "1.6.0", "clarabel": "0.9.0"}
SHA = "9f2c4e1ab37d5c0e8f16a2b4c6d8e0f1a3b5c7d9e1f3a5b7c9d1e3f5a7b9c1d3"

VDP_F = ["x2", "-x1 + x2*(1 - x1**2)"]
VDP_JF = [["0", "1"], ["-2*x1*x2 - 1", "1 - x1**2"]]
DUF_F = ["x2**3", "-x1"]
DUF_JF = [["0", "3*x2**2"], ["-1", "0"]]


# ----------------------------------------------------------------------------- helpers

def _grid_map(X: list[list[float]], fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
              nx: int = 61, ny: int = 61) -> dict:
    """A figure map {axes, x, y, values[ny][nx]} of fn over the first two coordinates."""
    xs = np.linspace(X[0][0], X[0][1], nx)
    ys = np.linspace(X[1][0], X[1][1], ny)
    gx, gy = np.meshgrid(xs, ys)
    vals = fn(gx, gy)
    values = [[("NaN" if not np.isfinite(v) else float(v)) for v in row] for row in vals]
    return {"axes": ["x1", "x2"], "x": xs.tolist(), "y": ys.tolist(), "values": values}


def _proof_boxes(X: list[list[float]], fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
                 slope: float, depth: int) -> dict:
    """Leaf boxes of a toy branch and bound on fn (centre value + slope * radius^2)."""
    lo = np.array([[X[0][0], X[1][0]]])
    hi = np.array([[X[0][1], X[1][1]]])
    leaves_lo, leaves_hi, status = [], [], []
    for level in range(depth + 1):
        c = (lo + hi) / 2
        r = np.linalg.norm(hi - lo, axis=1) / 2
        val = fn(c[:, 0], c[:, 1])
        proved = val + slope * r ** 2 < 0
        violated = val > 0
        last = level == depth
        done = proved | violated | last
        for mask, tag in ((proved, "proved"), (violated & ~proved, "violated"),
                          (last & ~proved & ~violated, "unknown")):
            leaves_lo.append(lo[mask])
            leaves_hi.append(hi[mask])
            status += [tag] * int(mask.sum())
        lo, hi = lo[~done], hi[~done]
        if len(lo) == 0:
            break
        # split along the longer side
        w = hi - lo
        axis = (w[:, 1] > w[:, 0]).astype(int)
        mid = (lo[np.arange(len(lo)), axis] + hi[np.arange(len(lo)), axis]) / 2
        lo2, hi1 = lo.copy(), hi.copy()
        hi1[np.arange(len(lo)), axis] = mid
        lo2[np.arange(len(lo)), axis] = mid
        lo, hi = np.concatenate([lo, lo2]), np.concatenate([hi1, hi])
    return {"axes": ["x1", "x2"], "lo": np.concatenate(leaves_lo).tolist(),
            "hi": np.concatenate(leaves_hi).tolist(), "status": status}


def _simulate(f: Callable[[np.ndarray], np.ndarray], gain: np.ndarray, x0: np.ndarray,
              xhat0: np.ndarray, *, vbar: float, gaussian: bool, T: float = 10.0,
              dt: float = 0.01, keep: int = 201, seed: int = 0) -> tuple[np.ndarray, ...]:
    """RK4 of plant x' = f(x) and observer xhat' = f(xhat) + gain (y + v - xhat1).

    Vectorised over initial conditions [R, n]; returns t [T], x and xhat [R, T, n].
    """
    rng = np.random.default_rng(seed)
    steps = int(round(T / dt))
    x, xh = x0.astype(float).copy(), xhat0.astype(float).copy()
    xs, xhs = [x.copy()], [xh.copy()]
    for _ in range(steps):
        v = (rng.normal(0, vbar, size=(len(x), 1)) if gaussian
             else rng.uniform(-vbar, vbar, size=(len(x), 1)))

        def obs(xh_, x_, v=v):
            return f(xh_) + (x_[:, :1] + v - xh_[:, :1]) * gain

        k1, m1 = f(x), obs(xh, x)
        k2, m2 = f(x + dt / 2 * k1), obs(xh + dt / 2 * m1, x + dt / 2 * k1)
        k3, m3 = f(x + dt / 2 * k2), obs(xh + dt / 2 * m2, x + dt / 2 * k2)
        k4, m4 = f(x + dt * k3), obs(xh + dt * m3, x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        xh = xh + dt / 6 * (m1 + 2 * m2 + 2 * m3 + m4)
        xs.append(x.copy())
        xhs.append(xh.copy())
    t = np.linspace(0, T, steps + 1)
    idx = np.linspace(0, steps, keep).round().astype(int)
    return t[idx], np.stack(xs, 1)[:, idx], np.stack(xhs, 1)[:, idx]


def _exit_time(t: np.ndarray, x: np.ndarray, xh: np.ndarray, X: np.ndarray,
               Y: np.ndarray) -> tuple[float | None, str]:
    """First time x or xhat leaves X, or h(x) = x1 leaves Y."""
    out_x = np.any((x < X[:, 0]) | (x > X[:, 1]), axis=1)
    out_xh = np.any((xh < X[:, 0]) | (xh > X[:, 1]), axis=1)
    out_y = (x[:, 0] < Y[0, 0]) | (x[:, 0] > Y[0, 1])
    bad = out_x | out_xh | out_y
    if not bad.any():
        return None, ""
    i = int(np.argmax(bad))
    if out_x[i]:
        j = int(np.argmax((x[i] < X[:, 0]) | (x[i] > X[:, 1])))
        return float(t[i]), f"x leaves X: |x{j + 1}| = {abs(x[i, j]):.2f} at t = {t[i]:.2f}"
    if out_xh[i]:
        return float(t[i]), f"xhat leaves X at t = {t[i]:.2f}"
    return float(t[i]), f"h(x) leaves Y: |y| = {abs(x[i, 0]):.2f} at t = {t[i]:.2f}"


def _runs(f, gain, X, Y, x0s, xh0s, vbar, labels, *, gaussian_last: bool,
          bound_fn: Callable[[np.ndarray, float], np.ndarray] | None,
          valid: bool) -> list[SimulationRun]:
    """Simulation runs with their error, bound, exits and max error/bound ratio."""
    Xa, Ya = np.asarray(X), np.asarray(Y)
    t, xb, xhb = _simulate(f, gain, np.asarray(x0s[:-1] if gaussian_last else x0s),
                           np.asarray(xh0s[:-1] if gaussian_last else xh0s),
                           vbar=vbar, gaussian=False)
    trajs = [(xb[i], xhb[i], "bounded") for i in range(len(xb))]
    if gaussian_last:
        _, xg, xhg = _simulate(f, gain, np.asarray(x0s[-1:]), np.asarray(xh0s[-1:]),
                               vbar=vbar, gaussian=True, seed=1)
        trajs.append((xg[0], xhg[0], "gaussian"))
    runs = []
    for (x, xh, noise), label, x0, xh0 in zip(trajs, labels, x0s, xh0s):
        err = np.linalg.norm(x - xh, axis=1)
        exit_time, reason = _exit_time(t, x, xh, Xa, Ya)
        if noise == "gaussian":
            reason = ("Gaussian noise has no bound vbar (condition (c)); "
                      + (reason or "the state stays in X")).strip()
        within = valid and noise == "bounded"
        bound = bound_fn(t, float(err[0])) if (bound_fn is not None and within) else None
        ratio, breach = None, False
        if bound is not None:
            upto = t <= (exit_time if exit_time is not None else np.inf)
            ratio = float(np.max(err[upto] / bound[upto]))
            breach = ratio > 1.0
        runs.append(SimulationRun(
            label=label, x0=list(map(float, x0)), xhat0=list(map(float, xh0)), noise=noise,
            within_conditions=within and exit_time is None, exit_time=exit_time,
            exit_reason=reason, max_ratio=ratio, breach=breach,
            mse=float(np.mean(err ** 2)), final_error=float(err[-1]), t=t.tolist(),
            error=err.tolist(), bound=[] if bound is None else bound.tolist(),
            x=x.tolist(), xhat=xh.tolist()))
    return runs


def _vdp_f(z: np.ndarray) -> np.ndarray:
    return np.stack([z[:, 1], -z[:, 0] + z[:, 1] * (1 - z[:, 0] ** 2)], axis=1)


def _duffing_f(z: np.ndarray) -> np.ndarray:
    return np.stack([z[:, 1] ** 3, -z[:, 0]], axis=1)


def _settings(**kw) -> dict:
    return to_jsonable(VerifySettings(**kw))


def _finish(checks: dict, required: list[str], settings: dict, allow_unknown: bool,
            **kw) -> Certificate:
    verdict, summary = decide_verdict(checks, required, allow_unknown)
    return Certificate(verdict=verdict, summary=summary, checks=checks, required=required,
                       settings=settings, **kw)


THEOREM3_FORMULA = ("||e(t)|| <= ||e(0)|| exp(-eta t) + eps_bar / (2 sqrt(eta)) "
                    "+ L vbar / (2 sqrt(eta)),  eta = lam - 2")
ISS_FORMULA = ("||e(t)|| <= ( exp(-2 lam t) W(0) + (1 - exp(-2 lam t)) ||P^1/2|| "
               "(eps_bar + L vbar) / (2 lam) ) / sqrt(lam_min(P))")
VALIDITY = [
    "(a) X is convex and x(s), xhat(s) stay in X for s <= t",
    "(b) the true output h(x(s)) stays in Y for s <= t",
    "(c) the measurement noise satisfies ||v(s)||_2 <= vbar (Gaussian noise has no vbar)",
    "(d) y_e = h(xhat) stays in Y (needed only because L is a local bound)",
]


# ----------------------------------------------------------------------------- CERTIFIED

def certified_certificate() -> Certificate:
    """A metric-P, structural-gain VdP design on an enlarged box: every check proved."""
    X = [[-2.5, 2.5], [-3.5, 3.5]]
    Y = [[-2.6, 2.6]]
    P = [[1.0, 0.31], [0.31, 0.16]]
    lam = 0.5
    Pn = np.array(P)
    eig = np.linalg.eigvalsh(Pn)
    kappa = float(eig[-1] / eig[0])
    lam_lo, lam_hi = 0.5213, 0.5702
    vbar = 0.05
    eps, L = 0.0, 6.81
    half = float(np.sqrt(eig[-1]))
    bias = half * (eps + L * vbar) / (2 * lam_lo) / np.sqrt(eig[0])
    gain = float(np.sqrt(kappa))
    bias_p = (eps + 3.0122 * vbar) / (2 * lam_lo) / np.sqrt(eig[0])

    def mpdi_fn(a, b):
        return (-0.0045 - 0.9 * (a / 2.5) ** 2 - 0.35 * (b / 3.5) ** 2
                + 0.02 * np.sin(2 * a) * np.cos(b))

    boxes = _proof_boxes(X, mpdi_fn, slope=3.0, depth=18)
    hist = [[0.0, 0.0], [2.1, 0.41], [5.0, 0.72], [9.8, 0.91], [15.2, 0.985], [19.4, 1.0]]
    mpdi = MpdiResult(
        status=Status.PROVED,
        message="D <= 0 proved on all of X x Y (sound upper bound -0.0031)",
        lower=-0.004512, upper=-0.003107,
        worst=Counterexample(xhat=[0.0213, -0.0412], y=[0.0731], value=-0.004512),
        counterexamples=[], violating_fraction=0.0, grid_points=1_000_000,
        adversarial_starts=64,
        proof=ProofStats(boxes_processed=184_733, boxes_per_second=9_522.3, seconds=19.4,
                         proved_volume_fraction=1.0, max_depth=23, budget_exhausted=False,
                         rounding="outward margin 4 n u ||C|| + Collatz-Wielandt radius",
                         volume_history=hist),
        seconds=27.8)
    rate = RateResult(status=Status.PROVED,
                      message="lam_cert in [0.5213, 0.5702] (design lam 0.5)",
                      lam_design=lam, sampled_upper=lam_hi, proved_lower=lam_lo,
                      worst=Counterexample(xhat=[0.02, -0.04], y=[0.07], value=lam_hi),
                      seconds=41.0)
    residual = ResidualResult(status=Status.PROVED,
                              message="k(x, h(x)) = 0 by construction (structural gain)",
                              sampled=0.0, upper=0.0, structural=True, worst=None, seconds=0.01)
    lip = LipschitzResult(
        status=Status.PROVED, message="L <= 6.81 (local interval bound; LipSDP 7.94)",
        lipsdp=7.9412, lipsdp_raw=7.9408, lipsdp_verified=True, lipsdp_lmi_max_eig=-2.1e-9,
        naive=214.77, sampled=6.0377, local_upper=6.8104, value=6.8104, which="local",
        solver={"name": "CLARABEL", "status": "optimal", "iterations": 31, "seconds": 0.84},
        seconds=3.9, lipsdp_P=3.0122)
    nec = NecessaryResult(
        status=Status.PROVED, message="q <= -0.0712 on the output manifold (proved)",
        q_max=-0.0934, q_upper=-0.0712, witness=[2.5, 0.0], witness_y=[2.5],
        rate_cap=0.7411, residual_price=None,
        explanation=("With this metric P and rate lam, the part of D that no gain can change "
                     "(the directions in the kernel of dh/dxhat) is negative everywhere on the "
                     "output manifold, so a gain with exact boundary condition can satisfy "
                     "the MPDI; the rate cap 0.741 bounds lam_cert for any such gain."),
        seconds=1.2)
    metric = MetricResult(status=Status.PROVED, message=f"P found by SDP (cond {kappa:.3g})",
                          P=P, condition_number=kappa, margin=0.012, lam=lam,
                          K=[[1.93], [4.12]],
                          solver={"name": "CLARABEL", "status": "optimal"}, seconds=0.6)
    t3 = BoundResult(name="Theorem 3 (as stated)", applicable=False,
                     reason=f"stated for P = I; this design uses a metric P (cond {kappa:.3g}) "
                            "and lam_cert = 0.521 <= 2",
                     rate=None, gain=None, bias=None, bias_per_unit_noise=None,
                     formula=THEOREM3_FORMULA)
    iss = BoundResult(name="ISS bound", applicable=True,
                      reason="D <= 0 proved on X x Y with lam_cert >= 0.5213 > 0",
                      rate=2 * lam_lo, gain=gain, bias=float(bias),
                      bias_per_unit_noise=float(bias / vbar), formula=ISS_FORMULA)
    iss_m = BoundResult(name="ISS bound, P^1/2-weighted", applicable=True,
                        reason="as the ISS bound, with eps_bar_P = 0 and L_P = 3.01",
                        rate=2 * lam_lo, gain=gain, bias=float(bias_p),
                        bias_per_unit_noise=float(bias_p / vbar), formula=ISS_FORMULA)
    bounds = BoundsResult(status=Status.PROVED,
                          message=f"ISS bound applies: ultimate error bound {bias_p:.2g} "
                                  f"(P-weighted) at vbar {vbar}",
                          vbar=vbar, lam_cert=lam_lo, eps_bar=eps, L=L, theorem3=t3, iss=iss,
                          iss_metric=iss_m, validity=VALIDITY, kappa_P=kappa)

    def bound_fn(t, e0):
        r = 2 * lam_lo
        return gain * np.exp(-r * t) * e0 + (1 - np.exp(-r * t)) * float(bias_p) + 1e-9

    x0s = [[1.0, 1.0], [-1.5, 0.5], [0.5, -2.0], [-1.0, 2.5]]
    xh0s = [[0.0, 0.0], [0.0, 0.0], [1.0, -1.0], [0.0, 0.0]]
    runs = _runs(_vdp_f, np.array([[1.93, 4.12]]), X, Y, x0s, xh0s, vbar,
                 ["ic-1", "ic-2", "ic-3", "source protocol (Gaussian)"],
                 gaussian_last=True, bound_fn=bound_fn, valid=True)
    sim = SimulationResult(status=Status.PASSED,
                           message="3 runs with bounded noise stay under the bound "
                                   "(max error/bound 0.62); 1 run outside the conditions",
                           runs=runs, seconds=2.4)
    checks = {"necessary": nec, "metric": metric, "mpdi": mpdi, "rate": rate,
              "residual": residual, "lipschitz": lip, "bounds": bounds, "simulation": sim}
    worst_ratio = max(r.max_ratio for r in runs if r.max_ratio is not None)
    sim.message = (f"{sum(r.max_ratio is not None for r in runs)} runs with bounded noise stay "
                   f"under the bound (max error/bound {worst_ratio:.2f}); 1 run outside the "
                   "conditions")
    system = {"name": "vdp-wide", "description": "Van der Pol oscillator on an enlarged box",
              "states": ["x1", "x2"], "outputs": ["y"], "f": VDP_F, "h": ["x1"],
              "X": X, "Y": Y, "lam": lam, "P": P, "jacobian_f": VDP_JF}
    figures = {
        "mpdi_map": _grid_map(X, mpdi_fn),
        "proof_boxes": boxes,
        "proof_history": hist,
        "necessary_map": _grid_map(X, lambda a, b: -0.0934 - 0.3 * (b / 3.5) ** 2 + 0 * a),
        "residual_map": _grid_map(X, lambda a, b: 0 * a),
    }
    return _finish(
        checks, ["mpdi", "rate", "bounds"],
        _settings(noise=vbar, required=("mpdi", "rate", "bounds"), sim_initial_conditions=4),
        False, system=system, lam=lam, P=P,
        network={"n": 2, "p": 1, "hidden": [30, 30, 30], "activation": "tanh",
                 "structure": "structural", "parameters": 2_072},
        checkpoint={"path": "runs/vdp-wide-metric.ckpt", "sha256": SHA,
                    "created": "2025-05-02T10:14:03+00:00",
                    "training": {"preset": "certifiable", "iterations": 3000,
                                 "final_loss": 1.2e-6, "cegis_rounds": 4}},
        versions=VERSIONS,
        timings={"necessary": 1.2, "metric": 0.6, "mpdi": 27.8, "rate": 41.0,
                 "residual": 0.01, "lipschitz": 3.9, "bounds": 0.0, "simulation": 2.4,
                 "total": 76.9},
        created="2025-05-02T10:16:11+00:00", figures=figures)


# ----------------------------------------------------------------------------- NOT CERTIFIED

NECESSARY_VDP_TEXT = (
    "With P = I and lam = 2.5, every C^1 gain that meets the boundary condition k(x, h(x)) = 0 "
    "must have dk/dxhat = -(dk/dy) dh/dxhat on the output manifold, so along the unmeasured "
    "direction v = (0, 1) the MPDI reads v^T D v = df2/dx2 + 2 lam = 1 - x1^2 + 5, whatever "
    "the network. At the witness x1 = 0 this is q = 6 > 0: no gain, however trained, can "
    "satisfy the MPDI and the boundary condition together with this P and lam. Any gain with "
    "exact boundary condition has lam_cert <= -0.5 (the rate cap); and if D <= 0 held "
    "everywhere, the residual would be at least 18 (chord x1 = 0, x2 in [-3, 3]), so the "
    "bias term eps_bar / (2 lam) >= 3.6 would make the bound useless on this box. Choose a "
    "metric P (certify check vdp --metric) or a smaller rate.")


def violated_vdp_certificate() -> Certificate:
    """The paper preset of VdP: MPDI violated (lam_max up to +7.7), no bound at all."""
    X = [[-2.0, 2.0], [-3.0, 3.0]]
    Y = [[-2.0, 2.0]]
    P = [[1.0, 0.0], [0.0, 1.0]]
    lam = 2.5

    def mpdi_fn(a, b):
        return 6.0 - a ** 2 + 1.7 * np.exp(-(a ** 2 + (b - 0.8) ** 2) / 1.5)

    cex_pts = [([0.0, 0.8], [0.03], 7.7), ([0.05, 0.74], [-0.02], 7.6962),
               ([-0.08, 0.86], [0.11], 7.6831), ([0.12, 0.69], [0.2], 7.6605),
               ([-0.15, 0.93], [-0.25], 7.6378)]
    cexs = [Counterexample(xhat=a, y=b, value=v) for a, b, v in cex_pts]
    mpdi = MpdiResult(
        status=Status.VIOLATED,
        message="MPDI violated: lam_max(D) = +7.7 > 0 at xhat = (0, 0.8), y = 0.03; "
                "93.1% of grid points violate",
        lower=7.7, upper=None, worst=cexs[0], counterexamples=cexs,
        violating_fraction=0.9312, grid_points=1_000_000, adversarial_starts=64,
        proof=None, seconds=6.3)
    rate = RateResult(status=Status.VIOLATED,
                      message="lam_cert <= -1.35 < 0: the observer does not contract "
                              "(design lam 2.5)",
                      lam_design=lam, sampled_upper=-1.35, proved_lower=None,
                      worst=cexs[0], seconds=0.9)
    residual = ResidualResult(status=Status.PROVED,
                              message="eps_bar in [0.3113, 0.4187]",
                              sampled=0.31128, upper=0.41869, structural=False,
                              worst=[1.93, -2.71], seconds=8.2)
    lip = LipschitzResult(
        status=Status.PROVED, message="L <= 12.33 (LipSDP, verified)",
        lipsdp=12.3301, lipsdp_raw=12.3297, lipsdp_verified=True, lipsdp_lmi_max_eig=-3.4e-9,
        naive=1_873.4, sampled=9.8211, local_upper=13.96, value=12.3301, which="lipsdp",
        solver={"name": "CLARABEL", "status": "optimal", "iterations": 42, "seconds": 1.7},
        seconds=6.6, lipsdp_P=12.3301)
    nec = NecessaryResult(
        status=Status.VIOLATED,
        message="q = +6 > 0 at x1 = 0: no C^1 gain satisfies MPDI and BC with P = I, lam = 2.5",
        q_max=6.0, q_upper=6.0000000000001, witness=[0.0, -3.0], witness_y=[0.0],
        rate_cap=-0.5, residual_price=18.0, explanation=NECESSARY_VDP_TEXT, seconds=0.4)
    t3 = BoundResult(name="Theorem 3 (as stated)", applicable=False,
                     reason="needs lam > 2 with lam = lam_cert; lam_cert <= -1.35 "
                            "(the design lam 2.5 is not what the network achieves)",
                     rate=None, gain=None, bias=None, bias_per_unit_noise=None,
                     formula=THEOREM3_FORMULA)
    iss = BoundResult(name="ISS bound", applicable=False,
                      reason="needs D <= 0 on X x Y and lam_cert > 0; MPDI violated",
                      rate=None, gain=None, bias=None, bias_per_unit_noise=None,
                      formula=ISS_FORMULA)
    bounds = BoundsResult(status=Status.VIOLATED,
                          message="no error bound: lam_cert <= -1.35 <= 0",
                          vbar=0.15, lam_cert=None, eps_bar=0.41869, L=12.3301,
                          theorem3=t3, iss=iss, iss_metric=None, validity=VALIDITY,
                          kappa_P=1.0)
    x0s = [[-1.0, 2.5], [1.0, 1.0], [0.5, -1.5], [-1.0, 2.5]]
    xh0s = [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]
    runs = _runs(_vdp_f, np.array([[2.4, 3.1]]), X, Y, x0s, xh0s, 0.15,
                 ["source x0 (bounded)", "ic-2", "ic-3", "source protocol (Gaussian)"],
                 gaussian_last=True, bound_fn=None, valid=False)
    n_exit = sum(r.exit_time is not None for r in runs)
    sim = SimulationResult(status=Status.UNKNOWN,
                           message=f"no bound to compare against; {n_exit} of {len(runs)} "
                                   "runs leave X or Y (limit cycle reaches |x1| = 2.01)",
                           runs=runs, seconds=1.9)
    checks = {"necessary": nec, "mpdi": mpdi, "rate": rate, "residual": residual,
              "lipschitz": lip, "bounds": bounds, "simulation": sim}
    system = {"name": "vdp", "description": "Van der Pol oscillator (mu = 1), position measured",
              "states": ["x1", "x2"], "outputs": ["y"], "f": VDP_F, "h": ["x1"],
              "X": X, "Y": Y, "lam": lam, "P": P, "jacobian_f": VDP_JF}
    figures = {
        "mpdi_map": _grid_map(X, mpdi_fn),
        "necessary_map": _grid_map(X, lambda a, b: 6.0 - a ** 2 + 0 * b),
        "residual_map": _grid_map(
            X, lambda a, b: 0.05 + 0.36 * np.abs(np.tanh(a * b / 3)) * (a / 2) ** 2),
    }
    return _finish(
        checks, ["mpdi"], _settings(sim_initial_conditions=4), False,
        system=system, lam=lam, P=P,
        network={"n": 2, "p": 1, "hidden": [30, 30, 30, 30, 30], "activation": "tanh",
                 "structure": "direct", "parameters": 3_932},
        checkpoint={"path": "vdp.ckpt", "sha256": SHA[::-1],
                    "created": "2025-05-01T08:00:00+00:00",
                    "training": {"preset": "paper", "adam_iterations": 500,
                                 "lbfgs_iterations": 500, "final_loss": 3.1e-4, "seed": 0}},
        versions=VERSIONS,
        timings={"necessary": 0.4, "mpdi": 6.3, "rate": 0.9, "residual": 8.2,
                 "lipschitz": 6.6, "bounds": 0.0, "simulation": 1.9, "total": 24.3},
        created="2025-05-01T08:03:12+00:00", figures=figures)


# ----------------------------------------------------------------------------- INCONCLUSIVE

def inconclusive_certificate() -> Certificate:
    """Reverse Duffing, metric design: no counterexample, proof budget spent (UNKNOWN)."""
    X = [[-1.0, 1.0], [-1.0, 1.0]]
    Y = [[-0.8, 0.8]]  # narrower than h(X): part of the necessary map is NaN
    P = [[1.0, 0.2], [0.2, 0.5]]
    lam = 0.3

    def mpdi_fn(a, b):
        return -0.02 - 0.3 * a ** 2 - 0.25 * (b - 0.6) ** 2 * (1 + a)

    boxes = _proof_boxes(X, lambda a, b: mpdi_fn(a, b) + 0.01999, slope=2.0, depth=13)
    hist = [[0.0, 0.0], [10.0, 0.55], [20.0, 0.81], [40.0, 0.94], [60.0, 0.973]]
    cell = Counterexample(xhat=[-0.02, 0.61], y=[0.1], value=-0.0201)
    mpdi = MpdiResult(
        status=Status.UNKNOWN,
        message="proof budget spent (proof_seconds=60); best upper bound +0.013; "
                "no counterexample found; raise proof_seconds or max_boxes",
        lower=-0.0201, upper=0.0131, worst=cell, counterexamples=[],
        violating_fraction=0.0, grid_points=250_000, adversarial_starts=64,
        proof=ProofStats(boxes_processed=611_420, boxes_per_second=10_190.3, seconds=60.0,
                         proved_volume_fraction=0.973, max_depth=31, budget_exhausted=True,
                         rounding="outward margin 4 n u ||C|| + Collatz-Wielandt radius",
                         volume_history=hist),
        seconds=64.2)
    rate = RateResult(status=Status.UNKNOWN, message="lam_cert <= 0.31; no proved lower bound",
                      lam_design=lam, sampled_upper=0.3101, proved_lower=None, worst=cell,
                      seconds=12.0)
    residual = ResidualResult(status=Status.PROVED, message="eps_bar in [0.0021, 0.0035]",
                              sampled=0.00208, upper=0.00347, structural=False,
                              worst=[0.8, -1.0], seconds=2.2)
    lip = LipschitzResult(
        status=Status.UNKNOWN, message="LipSDP not verified (LMI max eig +4.8e-4 after "
                                       "inflation); naive bound used",
        lipsdp=None, lipsdp_raw=3.17, lipsdp_verified=False, lipsdp_lmi_max_eig=4.8e-4,
        naive=96.2, sampled=2.92, local_upper=None, value=96.2, which="naive",
        solver={"name": "CLARABEL", "status": "optimal_inaccurate"}, seconds=10.0)
    nec = NecessaryResult(
        status=Status.PROVED, message="q <= -0.05 on the output manifold",
        q_max=-0.0721, q_upper=-0.0500, witness=[0.8, 0.0], witness_y=[0.8],
        rate_cap=0.44, residual_price=None,
        explanation=("The network-independent part of the MPDI is negative on the output "
                     "manifold {h(xhat) in Y}; points where h(xhat) leaves Y (|x1| > 0.8) "
                     "are outside the condition and shown blank."), seconds=0.3)
    t3 = BoundResult(name="Theorem 3 (as stated)", applicable=False,
                     reason="MPDI not proved; and lam_cert <= 0.31 <= 2", rate=None,
                     gain=None, bias=None, bias_per_unit_noise=None, formula=THEOREM3_FORMULA)
    iss = BoundResult(name="ISS bound", applicable=False,
                      reason="MPDI not proved (UNKNOWN): D <= 0 is an assumption of the bound",
                      rate=None, gain=None, bias=None, bias_per_unit_noise=None,
                      formula=ISS_FORMULA)
    bounds = BoundsResult(status=Status.UNKNOWN, message="no bound until the MPDI is proved",
                          vbar=0.05, lam_cert=None, eps_bar=0.00347, L=96.2, theorem3=t3,
                          iss=iss, iss_metric=None, validity=VALIDITY, kappa_P=2.79)
    x0s = [[0.5, 0.5], [-0.5, 0.5], [0.3, -0.4]]
    xh0s = [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]
    runs = _runs(_duffing_f, np.array([[1.2, 1.5]]), X, Y, x0s, xh0s, 0.05,
                 ["ic-1", "ic-2", "ic-3"], gaussian_last=False, bound_fn=None, valid=False)
    sim = SimulationResult(status=Status.SKIPPED, message="no bound to compare against",
                           runs=runs, seconds=1.0)
    checks = {"necessary": nec, "mpdi": mpdi, "rate": rate, "residual": residual,
              "lipschitz": lip, "bounds": bounds, "simulation": sim}
    system = {"name": "duffing", "description": "reverse Duffing oscillator, position measured",
              "states": ["x1", "x2"], "outputs": ["y"], "f": DUF_F, "h": ["x1"],
              "X": X, "Y": Y, "lam": lam, "P": P, "jacobian_f": DUF_JF}

    def nec_fn(a, b):
        q = -0.0721 - 0.2 * b ** 2 - 0.05 * a ** 2
        return np.where(np.abs(a) <= 0.8, q, np.nan)

    figures = {"mpdi_map": _grid_map(X, mpdi_fn), "proof_boxes": boxes, "proof_history": hist,
               "necessary_map": _grid_map(X, nec_fn),
               "residual_map": _grid_map(X, lambda a, b: 0.002 + 0.0012 * np.abs(a * b))}
    return _finish(
        checks, ["mpdi", "lipschitz"],
        _settings(grid_points=250_000, noise=0.05, required=("mpdi", "lipschitz"),
                  sim_initial_conditions=3), False,
        system=system, lam=lam, P=P,
        network={"n": 2, "p": 1, "hidden": [16, 16], "activation": "tanh",
                 "structure": "direct"},
        checkpoint={"path": "duffing.ckpt", "sha256": SHA[5:] + SHA[:5],
                    "created": "2025-05-03T12:00:00+00:00", "training": {}},
        versions=VERSIONS,
        timings={"necessary": 0.3, "mpdi": 64.2, "rate": 12.0, "residual": 2.2,
                 "lipschitz": 10.0, "simulation": 1.0, "total": 89.7},
        created="2025-05-03T12:01:30+00:00", figures=figures)


ALL = {"certified": certified_certificate, "violated": violated_vdp_certificate,
       "inconclusive": inconclusive_certificate}
