"""Outcome vocabulary and the result record of every check.

Logic-free dataclasses: each check fills one; the certificate gathers them. Numbers are
plain floats/lists so that every result round-trips through JSON unchanged. A bound that
was not computed is `None`, never a made-up value.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from certify.settings import CERTIFICATE_CHECK


class Status(str, enum.Enum):
    """How a check ended. PROVED is a sound result; PASSED means sampled evidence (simulation)
    found no problem, which is never called a proof; UNKNOWN is never a pass. NOT APPLICABLE:
    the question has no answer here (e.g. no error bound exists when lam_cert <= 0, or there
    is no bound to compare a simulation with), which establishes nothing, like UNKNOWN.
    SKIPPED: the user skipped the check. NOT RUN: the verdict was decided before it (a
    required check VIOLATED) and nothing asked for its numbers, so it was not run; it
    establishes nothing either."""

    PROVED = "PROVED"
    PASSED = "PASSED"
    VIOLATED = "VIOLATED"
    UNKNOWN = "UNKNOWN"
    SKIPPED = "SKIPPED"
    NOT_APPLICABLE = "NOT APPLICABLE"
    NOT_RUN = "NOT RUN"
    ERROR = "ERROR"


@dataclass
class Counterexample:
    """A point (xhat, y) and the value of the checked quantity there (float64).

    `sound_bound`: a sound lower bound of the quantity at the point (`certify.search.witness`); a
    point is a counterexample only when it is > 0. None when not computed."""

    xhat: list[float]
    y: list[float]
    value: float
    sound_bound: float | None = None


@dataclass
class ProofStats:
    """What the branch-and-bound prover did: effort, speed, and how soundness was kept."""

    boxes_processed: int = 0
    boxes_per_second: float = 0.0
    seconds: float = 0.0
    proved_volume_fraction: float = 0.0
    max_depth: int = 0
    budget_exhausted: bool = False
    #: the run's wall-clock cap (`max_seconds`) stopped it before its box budget did (its
    #: bound is sound but partial, and the check that ran it is UNKNOWN)
    stopped_by_cap: bool = False
    rounding: str = ""
    # (seconds since start, proved volume fraction) samples, for the report.
    volume_history: list[list[float]] = field(default_factory=list)
    # an unfinished decision proof: the boxes a complete one would evaluate, estimated by
    # random descents (`certify.search.tree_estimate`; not a bound), and its relative standard error
    estimated_boxes: float | None = None
    estimate_rel_stderr: float | None = None
    # per stage of the box bound (`certify.enclose.stages`): the boxes it bounded and of those
    # the ones it closed, over the proof's rounds ({} for bounds without stages)
    stages: dict[str, dict[str, int]] = field(default_factory=dict)

    @classmethod
    def total(cls, parts: list[ProofStats]) -> ProofStats | None:
        """The effort of several proofs of one check together: boxes and seconds summed,
        the largest depth, `budget_exhausted` and `stopped_by_cap` if any part's (None
        without parts)."""
        parts = [p for p in parts if p is not None]
        if not parts:
            return None
        boxes = sum(p.boxes_processed for p in parts)
        seconds = sum(p.seconds for p in parts)
        return cls(boxes_processed=boxes, seconds=seconds,
                   boxes_per_second=boxes / seconds if seconds > 0 else 0.0,
                   max_depth=max(p.max_depth for p in parts),
                   budget_exhausted=any(p.budget_exhausted for p in parts),
                   stopped_by_cap=any(p.stopped_by_cap for p in parts),
                   rounding=parts[0].rounding)

    def seconds_to_finish(self) -> float | None:
        """Seconds a complete proof still needs at this run's speed, from the estimate of an
        unfinished proof (None without an estimate or a measured speed)."""
        boxes = self.estimated_boxes
        if boxes is None or not math.isfinite(boxes) or not self.boxes_per_second > 0:
            return None
        return max(boxes - self.boxes_processed, 0.0) / self.boxes_per_second


@dataclass
class MpdiResult:
    """MPDI D(xhat, y) <= 0 over X x Y: falsification (lower) and proof (upper) sides."""

    status: Status
    message: str
    lower: float  # largest lam_max(D) found by grid + adversarial search
    upper: float | None  # sound upper bound on max lam_max(D) (None: no proof attempted)
    worst: Counterexample | None = None
    counterexamples: list[Counterexample] = field(default_factory=list)
    violating_fraction: float = 0.0
    grid_points: int = 0
    adversarial_starts: int = 0
    proof: ProofStats | None = None
    seconds: float = 0.0


@dataclass
class RateResult:
    """Certified contraction rate: lam_cert lies in [proved_lower, sampled_upper]."""

    status: Status
    message: str
    lam_design: float
    sampled_upper: float  # min over sampled points of the pointwise rate (>= lam_cert)
    proved_lower: float | None  # proved: MPDI at the design lam, or B&B on the rate itself
    worst: Counterexample | None = None
    seconds: float = 0.0
    #: the effort of its proofs together (`ProofStats.total`; None: no proof ran)
    proof: ProofStats | None = None


@dataclass
class ResidualResult:
    """Boundary-condition residual eps_bar = sup_X ||k(x, h(x))||."""

    status: Status
    message: str
    sampled: float  # sampled + adversarial lower value
    upper: float | None  # sound upper bound (interval B&B over X)
    structural: bool = False  # zero by construction of the architecture
    worst: list[float] | None = None
    seconds: float = 0.0
    #: sound upper bound of sup_X ||P^(1/2) k(x, h(x))|| (None: not established)
    upper_P: float | None = None
    #: the effort of its proofs together (`ProofStats.total`; None: no proof ran)
    proof: ProofStats | None = None


@dataclass
class LipschitzResult:
    """Lipschitz constant of k in y, uniformly in xhat: several bounds side by side."""

    status: Status
    message: str
    lipsdp: float | None  # verified LipSDP bound (None: not verified / failed)
    lipsdp_raw: float | None  # the solver's value before the re-check
    lipsdp_verified: bool
    lipsdp_lmi_max_eig: float | None  # largest eigenvalue of the rebuilt LMI (<= 0 to verify)
    naive: float  # product of spectral norms
    sampled: float  # lower bound: max ||dk/dy||_2 found
    local_upper: float | None  # sup ||dk/dy||_2 over X x Y by the interval prover
    value: float | None  # the bound used downstream (smallest sound one)
    which: str = ""  # "lipsdp" | "local" | "naive" | "structural"
    solver: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    # the same constants for P^(1/2) k (the sharper ISS variant)
    lipsdp_P: float | None = None
    #: L_P: a sound bound on the Lipschitz constant of P^(1/2) k in y, the smaller of the
    #: metric-weighted LipSDP (global) and the local branch and bound of ||P^(1/2) dk/dy||
    L_P: float | None = None
    L_P_which: str = ""  # "lipsdp" | "local" | "" (not established)
    #: the local sup over X x Y of ||P^(1/2) dk/dy||_2 (None: not run or not closed)
    local_upper_P: float | None = None
    #: the effort of its proofs together (`ProofStats.total`; None: no proof ran)
    proof: ProofStats | None = None


@dataclass
class NecessaryResult:
    """Network-independent pre-flight: q(xhat) <= 0 on the output manifold (METHOD 3.5)."""

    status: Status
    message: str
    q_max: float  # largest q found (sampled + local search)
    q_upper: float | None  # sound upper bound over the manifold
    witness: list[float] | None  # xhat where q_max is attained
    witness_y: list[float] | None
    rate_cap: float | None  # lam_cert <= rate_cap for any gain with exact BC
    residual_price: float | None  # eps_bar lower bound if D <= 0 everywhere (linear h)
    explanation: str = ""
    seconds: float = 0.0


@dataclass
class MetricResult:
    """A constant metric P found by SDP (or the reason none exists)."""

    status: Status
    message: str
    P: list[list[float]] | None
    condition_number: float | None
    margin: float
    lam: float
    K: list[list[float]] | None = None  # joint output-injection gain (LMI observer)
    solver: dict[str, Any] = field(default_factory=dict)
    witness: list[float] | None = None
    seconds: float = 0.0
    witness_y: list[float] | None = None  # y = h(witness) where no constant P can work


@dataclass
class BoundResult:
    """One error bound ||e(t)|| <= a e^(-r t) ||e0|| + b, with its validity conditions."""

    name: str
    applicable: bool
    reason: str  # why (not) applicable
    rate: float | None  # exponential rate r in the bound
    gain: float | None  # multiplier on ||e(0)|| (or on W(0))
    bias: float | None  # ultimate bound b at vbar
    bias_per_unit_noise: float | None  # d b / d vbar
    formula: str = ""
    #: a bound in stages (the metric that follows the state, `certify.prove.metric`): after
    #: the dissipation bound's settle time, piece k holds from `start` seconds on:
    #: ||e|| <= gain sqrt(e^(-alpha (t - start)) entry + (1 - e^(-alpha (t - start))) v_inf),
    #: dicts with keys start, alpha, entry, v_inf, tau; None for a one-piece bound
    pieces: list[dict] | None = None
    #: limits of |e_i| as t -> infinity where the bound has its own (None: from P)
    components: list[float] | None = None


@dataclass
class BoundsResult:
    """Theorem 3 as stated and the ISS ("tight") bound, at noise level vbar."""

    status: Status
    message: str
    vbar: float
    lam_cert: float | None
    eps_bar: float | None
    L: float | None
    theorem3: BoundResult | None
    iss: BoundResult | None
    iss_metric: BoundResult | None  # the sharper P^(1/2)-weighted variant
    validity: list[str] = field(default_factory=list)
    kappa_P: float = 1.0
    L_is_local: bool = False  # L holds only for y in Y: condition (d) applies
    #: half the diagonal of X (Euclidean): an error bound above it says little
    box_half_diagonal: float | None = None
    #: the headline bound exceeds `box_half_diagonal`: valid but vacuous
    vacuous: bool = False
    #: the joint dissipation bound (`certify.checks.dissipation`): V' <= -alpha V + mu |v|^2
    dissipation: BoundResult | None = None
    #: the bound with a metric that follows the state (`certify.checks.metric_bound`), in
    #: stages after the dissipation bound
    metric: BoundResult | None = None
    #: the headline, from the applicable bound with the smallest ultimate value (`best`):
    #: ||e(t)|| <= `headline` for every t >= `settle_time` from any start with x, xhat in X,
    #: and |e_i(t)| <= `per_component`[i] * `headline` / `ultimate` likewise
    best: str = ""
    ultimate: float | None = None  # the limit of the best bound as t -> infinity
    headline: float | None = None  # ultimate * HEADLINE_MARGIN: reached at settle_time
    settle_time: float | None = None
    per_component: list[float] | None = None  # ultimate bounds on |e_i|, i = 1..n
    #: the validity region (`certify.prove.error_bound.validity_region`): for every x(0) in
    #: the region R proved forward invariant (`region`, in words) and ||e(0)||_2 <= `r0`
    #: (||P^(1/2) e(0)|| <= `r0_W`), xhat stays in X and the conditions `proved_conditions`
    #: ("a", "b" and "d" where proved) hold for all t, so ||e(t)|| <= `headline` for every
    #: t >= `region_settle_time`; `region` "" and `region_reason` why when there is none
    region: str = ""
    r0: float | None = None
    r0_W: float | None = None
    region_settle_time: float | None = None
    proved_conditions: list[str] = field(default_factory=list)
    region_reason: str = ""

    def bounds(self) -> list[BoundResult]:
        """Every bound computed, applicable or not, in a fixed order."""
        return [b for b in (self.theorem3, self.iss, self.iss_metric, self.dissipation,
                            self.metric) if b is not None]


@dataclass
class DissipationResult:
    """The dissipation certificate: with V = e^T P e, the proved inequality
    V' <= -alpha V + mu ||v||^2 (+ mu_residual ||P^(1/2) r||^2 for a direct gain, r its
    residual, with `eps_bar` >= sup ||P^(1/2) r||), so that V -> at most
    (mu vbar^2 + mu_residual eps_bar^2) / alpha.

    `route`: "path" (one proof with dk/dy at the same point as the contraction) or "cover"
    (one proof per piece of a cover of dk/dy; None in certificates before the path route);
    `vertices` counts the pieces proved (1 for the path); `candidates` records each
    (alpha, mu) tried, with the sampled bound it aimed at, the route and the prover's
    verdict (dicts with keys route, alpha, mu, bound, status)."""

    status: Status
    message: str
    alpha: float | None = None
    mu: float | None = None
    mu_residual: float | None = None
    eps_bar: float | None = None
    vertices: int = 0
    candidates: list[dict] = field(default_factory=list)
    boxes: int = 0
    seconds: float = 0.0
    #: the effort of its proofs together (`ProofStats.total`; None: no proof ran)
    proof: ProofStats | None = None
    route: str | None = None



@dataclass
class MetricBoundResult:
    """The error bound with a metric that follows the state (`certify.prove.metric`): the
    metric (`PolyMetric.to_dict`), its proved constants (m_min: M >= m_min I; a: M <= a P;
    gamma_h and gamma per state: the paths' reach), the stages (dicts with keys tau, alpha,
    mu, entry, v_inf, boxes), the plant box in which the bound holds after the first stage,
    and the ultimate bound on ||e|| at the settings' noise (`ultimate`)."""

    status: Status
    message: str
    metric: dict[str, Any] | None = None
    m_min: float | None = None
    a: float | None = None
    gamma_h: float | None = None
    gamma: list[float] = field(default_factory=list)
    stages: list[dict] = field(default_factory=list)
    plant_box: list[list[float]] | None = None
    ultimate: float | None = None
    boxes: int = 0
    candidates: list[dict] = field(default_factory=list)
    seconds: float = 0.0


@dataclass
class InvarianceResult:
    """Forward invariance of a plant region R inside X (`certify.prove.invariance`).

    `region`: R as plain data (`certify.spec.region.Region.to_dict`: kind, origin "spec" or
    "found", vertices / box / V and level); `hull` [n][2]: proved outer bounds of R's
    component ranges; `output_range` [p][2]: an outer enclosure of h over R; `margin`: the
    largest proved upper bound of the outward speed on R's boundary (< 0); `witness`: a
    boundary point where the flow provably leaves R (VIOLATED). From the plant simulated
    alone: `attractor` (its kind: "equilibrium", "cycle", "other", "none"), `attractor_box`
    (the box of its samples: evidence, not proof), `attractor_leaves_box` (that box is not
    inside X) and `suggested_box` (a box holding it with a margin); `candidates`: the regions
    tried (dicts with keys kind, how, status, message)."""

    status: Status
    message: str
    region: dict[str, Any] | None = None
    hull: list[list[float]] | None = None
    output_range: list[list[float]] | None = None
    margin: float | None = None
    witness: list[float] | None = None
    attractor: str = ""
    attractor_box: list[list[float]] | None = None
    attractor_leaves_box: bool = False
    suggested_box: list[list[float]] | None = None
    candidates: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    #: the effort of its proofs together (None: no proof ran)
    proof: ProofStats | None = None


@dataclass
class SimulationRun:
    """One simulated trajectory of plant + observer."""

    label: str
    x0: list[float]
    xhat0: list[float]
    noise: str  # "bounded" | "gaussian"
    within_conditions: bool  # whether the theorem's conditions can apply at all
    exit_time: float | None  # first time a validity condition failed (None: never)
    exit_reason: str
    max_ratio: float | None  # max over valid times of error / bound (> 1 is a breach)
    breach: bool
    mse: float
    final_error: float
    t: list[float] = field(default_factory=list)
    error: list[float] = field(default_factory=list)
    bound: list[float] = field(default_factory=list)
    x: list[list[float]] = field(default_factory=list)
    xhat: list[list[float]] = field(default_factory=list)
    # allowance for the integrator's error in the comparison (estimated by step doubling)
    tolerance: float = 0.0
    #: how the start was chosen (certify.simulate.starts), in words
    start: str = ""
    #: length of the valid window [0, first exit) in seconds (the horizon if never left)
    window: float | None = None
    #: "uniform" (random directions of norm vbar, held a few steps), "switching" (chosen
    #: from the state to push the error up, certify.simulate.noise) or "gaussian"
    noise_kind: str = ""
    #: the largest ||v(t)||_2 of the run (<= vbar for bounded noise; None: Gaussian)
    max_noise: float | None = None
    #: the valid window in time constants of the best bound (None: no bound)
    time_constants: float | None = None
    #: the headline's settling time T (from the worst start in X; seconds): the peak is
    #: taken after it
    settle_time: float | None = None
    #: the largest ||e|| over [settle_time, first exit) (None: the run left the conditions
    #: before it settled, or no bound), when it happened, and max |e_i| over the same times
    peak_error: float | None = None
    peak_time: float | None = None
    peak_components: list[float] = field(default_factory=list)
    #: the run's own bound curve at peak_time, and the bound that holds after settling
    #: (the headline B); conservatism = B / peak_error (>= 1 unless the bound is breached)
    bound_at_peak: float | None = None
    bound_after_settling: float | None = None
    conservatism: float | None = None


@dataclass
class SimulationResult:
    """Simulation check: the observed error against the proved bound."""

    status: Status
    message: str
    runs: list[SimulationRun] = field(default_factory=list)
    seconds: float = 0.0
    #: one time constant of the best bound (1/(2 lam_cert) for the ISS bounds, 2/alpha for
    #: the dissipation bound; None: no bound); a valid window shorter than it compares
    #: little, and when every window is, the check is inconclusive
    time_constant: float | None = None
    #: the simulated horizon (s); extended beyond sim_time when it was not set and the
    #: bound is slow (horizon_note says why, or that a set sim_time is short)
    horizon: float | None = None
    horizon_extended: bool = False
    horizon_note: str = ""
    #: the bound the runs' peaks are compared with: its name and the headline value B
    bound_name: str = ""
    headline: float | None = None
    #: the largest peak after settling over the bounded runs, its run, and B / that peak
    peak_error: float | None = None
    peak_run: str = ""
    conservatism: float | None = None
    #: bounded runs that stayed valid for at least `min_time_constants` time constants
    long_runs: int = 0
    min_time_constants: float = 5.0


@dataclass
class CheckFailure:
    """A check that produced no result of its own: it raised (ERROR, with the exception's
    type and message) or its inputs were missing (NOT APPLICABLE, and why).

    `failed` marks the record in JSON, where it stands in place of the check's own result.
    """

    status: Status
    message: str
    error_type: str = ""  # the exception's class name; "" when not applicable
    seconds: float = 0.0
    failed: bool = True


RESULT_TYPES: dict[str, type] = {
    "mpdi": MpdiResult,
    "rate": RateResult,
    "residual": ResidualResult,
    "lipschitz": LipschitzResult,
    "necessary": NecessaryResult,
    "metric": MetricResult,
    "dissipation": DissipationResult,
    "metric_bound": MetricBoundResult,
    "invariance": InvarianceResult,
    "bounds": BoundsResult,
    "simulation": SimulationResult,
}


def decide_verdict(checks: dict[str, Any], required: list[str],
                   allow_unknown: bool) -> tuple[str, str]:
    """Verdict and a one-line summary from the required checks' statuses.

    The MPDI is the certificate: it is always required (added to `required` should a caller
    have dropped it) and CERTIFIED needs it PROVED, whatever `allow_unknown` says: that waiver
    is for the other required checks, never for the certificate itself.

    Any required VIOLATED -> NOT CERTIFIED (a counterexample stands on its own); else any
    required ERROR (the check failed internally: nothing was established either way) ->
    INCONCLUSIVE, whatever `allow_unknown` says; else any required UNKNOWN (or SKIPPED, not
    run, NOT APPLICABLE) -> INCONCLUSIVE unless `allow_unknown` (never for the MPDI); else
    CERTIFIED. Checks that are not required never change the verdict; one in ERROR is named
    in the summary, and so are the checks NOT RUN once the verdict was decided.
    """
    if CERTIFICATE_CHECK not in required:
        required = [CERTIFICATE_CHECK, *required]

    def status(n: str) -> Status | None:
        return checks[n].status if n in checks else None

    violated = [n for n in required if status(n) == Status.VIOLATED]
    errors = [n for n in required if status(n) == Status.ERROR]
    unknown = [n for n in required if status(n) in (None, Status.UNKNOWN, Status.SKIPPED,
                                                    Status.NOT_APPLICABLE, Status.NOT_RUN)]
    other_errors = [n for n in checks if n not in required and status(n) == Status.ERROR]
    aside = (f"; not required, ended in ERROR: {', '.join(other_errors)}"
             if other_errors else "")
    if violated:
        not_run = [n for n in checks if status(n) == Status.NOT_RUN]
        after = (f"; not run, the verdict being decided: {', '.join(not_run)}" if not_run
                 else "")
        return "NOT CERTIFIED", "failed: " + ", ".join(
            f"{n} ({checks[n].status.value})" for n in violated) + aside + after
    if errors:
        return "INCONCLUSIVE", ("check error: " + ", ".join(errors) + " ended in ERROR "
                                "(internal failure, see its message)"
                                + (f"; not established: {', '.join(unknown)}" if unknown
                                   else "") + aside)
    mpdi = status(CERTIFICATE_CHECK)
    if mpdi != Status.PROVED:
        return "INCONCLUSIVE", (f"not established: {CERTIFICATE_CHECK} "
                                f"({mpdi.value if mpdi is not None else 'not run'}): the MPDI "
                                "is the certificate and must be PROVED (allow_unknown never "
                                "waives it)" + aside)
    if unknown and not allow_unknown:
        return "INCONCLUSIVE", "not established: " + ", ".join(unknown) + aside
    note = f" (allowed unknown: {', '.join(unknown)})" if unknown else ""
    return "CERTIFIED", "all required checks proved: " + ", ".join(required) + note + aside


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, enums and containers to plain JSON types (NaN/Inf kept as strings)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, enum.Enum):
        return obj.value
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, float):
        if obj != obj:
            return "NaN"
        if obj in (float("inf"), float("-inf")):
            return "Infinity" if obj > 0 else "-Infinity"
        return obj
    if hasattr(obj, "item") and callable(obj.item):  # numpy / torch scalars
        return to_jsonable(obj.item())
    return obj


_SPECIAL = {"NaN": float("nan"), "Infinity": float("inf"), "-Infinity": float("-inf")}


def result_from_jsonable(name: str, data: Any) -> Any:
    """A check's result from its JSON form: its own type, or a `CheckFailure`."""
    if isinstance(data, dict) and data.get("failed") is True:
        return from_jsonable(CheckFailure, data)
    return from_jsonable(RESULT_TYPES[name], data)


def from_jsonable(cls: Any, data: Any) -> Any:
    """Inverse of `to_jsonable` for the annotated type `cls`."""
    if data is None:
        return None
    origin = typing.get_origin(cls)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(cls) if a is not type(None)]
        return from_jsonable(args[0], data) if len(args) == 1 else data
    if origin is list:
        (inner,) = typing.get_args(cls) or (Any,)
        return [from_jsonable(inner, v) for v in data]
    if origin is dict:
        args = typing.get_args(cls)
        inner = args[1] if len(args) == 2 else Any
        return {k: from_jsonable(inner, v) for k, v in data.items()}
    if isinstance(cls, type) and issubclass(cls, enum.Enum):
        return cls(data)
    if dataclasses.is_dataclass(cls):
        hints = typing.get_type_hints(cls)
        kwargs = {f.name: from_jsonable(hints[f.name], data[f.name])
                  for f in dataclasses.fields(cls) if f.name in data}
        return cls(**kwargs)
    if cls is float:
        return _SPECIAL.get(data, data) if isinstance(data, str) else float(data)
    return data
