"""The `invariance` check: a plant region R inside X, proved forward invariant.

Every error bound holds while the plant and the observer stay in X (condition (a)); a
simulation can only look. This check proves the plant's part: a region R inside X that no
trajectory of x' = f(x) leaves (`certify.prove.invariance`), the spec's own ([invariance],
`certify.spec.region`) or, without one, one certify finds around the plant's attractor
(simulated from points of X: a Lyapunov ellipse around an equilibrium, a polygon around a
cycle for n = 2). The bounds check then derives the initial errors for which the observer
stays in X too (`certify.prove.error_bound.validity_region`).

It also says where the plant goes: the box of its simulated attractor, whether that leaves X
(then no bound can hold for a plant on it) and a box that holds it with a margin.

Status: PROVED (a region inside X is forward invariant), VIOLATED (the spec's region is not:
a boundary point where the flow provably leaves it), UNKNOWN otherwise (no region proved,
or the one proved is not inside X), with the reason.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from certify.checks.base import Check, Context, setting_quantity
from certify.presentation import Presentation, Quantity
from certify.results import InvarianceResult, ProofStats, Status
from certify.settings import DEFAULTS

#: the suggested box: the attractor's box widened by this fraction of its width on each
#: side, then rounded outwards to two significant digits of the width
SUGGESTED_MARGIN = 0.1


def box_text(box: Any, names: list[str] | None = None) -> str:
    """'x1 in [-2.2, 2.2], x2 in [-2.9, 2.9]' (bounds to 4 digits: for words, not proofs)."""
    rows = np.asarray(box, dtype=np.float64)
    names = names or [f"x{i + 1}" for i in range(rows.shape[0])]
    return ", ".join(f"{n} in [{lo:.4g}, {hi:.4g}]" for n, (lo, hi) in zip(names, rows))


def suggested_box(box: np.ndarray) -> np.ndarray:
    """`box` [n, 2] widened by `SUGGESTED_MARGIN` of its width per side, rounded outwards to
    two significant digits of the width."""
    out = np.empty_like(box)
    for i, (lo, hi) in enumerate(box):
        width = max(float(hi - lo), 1e-12)
        step = 10.0 ** (math.floor(math.log10(width)) - 1)
        out[i, 0] = math.floor((lo - SUGGESTED_MARGIN * width) / step) * step
        out[i, 1] = math.ceil((hi + SUGGESTED_MARGIN * width) / step) * step
    return np.round(out, 12)


def inside(box: np.ndarray, X: np.ndarray) -> bool:
    return bool(np.all(box[:, 0] >= X[:, 0]) and np.all(box[:, 1] <= X[:, 1]))


def check_invariance(system: Any, *, budget: int = DEFAULTS.invariance_boxes,
                     seed: int = 0) -> InvarianceResult:
    """Prove a region R inside X forward invariant (the spec's, else one found around the
    simulated attractor) and describe the attractor (see the module docstring)."""
    from certify.prove import invariance as inv
    from certify.simulate.integrate import simulate_plant

    t0 = time.perf_counter()
    X = np.asarray(system.X, dtype=np.float64)
    names = list(system.states)

    def simulate(x0: np.ndarray, dt: float, steps: int) -> np.ndarray:
        return simulate_plant(system, x0, dt=dt, steps=steps).numpy()

    attractor = inv.locate_attractor(system, X, simulate, seed=seed)
    leaves = attractor.box is not None and not inside(attractor.box, X)
    suggest = suggested_box(attractor.box) if leaves else None
    where = ""
    if attractor.box is not None:
        where = (f"the plant's simulated attractor ({attractor.kind}) lies in "
                 f"{box_text(attractor.box, names)}"
                 + (f": it leaves X; a box that holds it: {box_text(suggest, names)}"
                    if leaves else ", inside X"))
    elif attractor.note:
        where = attractor.note

    tries = ([(system.invariance, "given by the spec")] if system.invariance is not None
             else inv.candidates(system, attractor, X))
    tried: list[dict] = []
    used, proof = 0, None
    chosen = None
    for region, how in tries:
        if used >= budget:
            break
        proof = inv.prove_region(system, region, X, budget - used)
        used += proof.boxes
        tried.append({"kind": region.kind, "how": how, "status": proof.status.value,
                      "message": proof.message})
        if proof.status != Status.UNKNOWN or system.invariance is not None:
            chosen = (region, how, proof)
            break
    stats = ProofStats(boxes_processed=used, seconds=time.perf_counter() - t0,
                       budget_exhausted=used >= budget)
    result = InvarianceResult(
        status=Status.UNKNOWN, message="", attractor=attractor.kind,
        attractor_box=None if attractor.box is None else attractor.box.tolist(),
        attractor_leaves_box=bool(leaves),
        suggested_box=None if suggest is None else suggest.tolist(), candidates=tried,
        proof=stats)
    if chosen is None:
        if tried:
            why = (f"none of the {len(tried)} regions tried was proved forward invariant "
                   f"(the last: {tried[-1]['message']})")
        else:
            why = "no region to try: " + (attractor.note or "no attractor found")
        result.message = f"no invariant region: {why}" + (f"; {where}" if where else "")
        return result
    region, how, proof = chosen
    result.region = region.to_dict()
    result.witness = proof.witness
    result.margin = proof.margin
    if proof.hull is not None:
        result.hull = proof.hull.tolist()
    if proof.output_range is not None:
        result.output_range = proof.output_range.tolist()
    if proof.status == Status.VIOLATED:
        result.status = Status.VIOLATED
        result.message = proof.message + (f"; {where}" if where else "")
        return result
    if proof.status != Status.PROVED:
        result.message = proof.message + (f"; {where}" if where else "")
        return result
    held = proof.hull is not None and inside(proof.hull, X)
    reach = ("" if proof.hull is None else f"; it lies in {box_text(proof.hull, names)}")
    if not held:
        result.message = (f"{region.describe()} ({how}) is forward invariant but not inside X"
                          f"{reach}, so it gives no validity region; " + where)
        return result
    speed = "" if proof.margin is None else f", outward speed <= {proof.margin:.3g}"
    result.status = Status.PROVED
    result.message = (f"{region.describe()} ({how}) is forward invariant and inside X"
                      f"{reach}: the flow crosses its boundary inwards everywhere (proved, "
                      f"{proof.boxes} pieces{speed})" + (f"; {where}" if where else ""))
    return result


class InvarianceCheck(Check):
    """A plant region inside X, proved forward invariant; where the attractor lies."""

    name = "invariance"
    title = "Forward invariance of a plant region"
    result_type = InvarianceResult
    reads = ("invariance_boxes", "seed")

    def run(self, context: Context) -> InvarianceResult:
        return check_invariance(context.problem.system,
                                budget=context.settings.invariance_boxes,
                                seed=context.settings.seed)

    def present(self, r: InvarianceResult, certificate: Any) -> Presentation:
        names = (getattr(certificate, "system", None) or {}).get("states")
        region = r.region or {}
        kind = region.get("kind", "")
        what = {"polygon": f"polygon of {len(region.get('vertices') or [])} vertices",
                "box": "box", "sublevel": f"{{{region.get('V')} <= {region.get('level')}}}"
                }.get(kind, "none")
        origin = {"spec": "given by the spec", "found": "found around the attractor"}.get(
            region.get("origin", ""), "")
        hull = box_text(r.hull, names) if r.hull else None
        att = box_text(r.attractor_box, names) if r.attractor_box else None
        suggest = box_text(r.suggested_box, names) if r.suggested_box else None
        facts = (Quantity("Status", r.status.value),
                 Quantity("Region R", what + (f" ({origin})" if origin else "")),
                 Quantity("R lies in", hull, "not bounded"),
                 Quantity("h over R in", box_text(r.output_range, list(
                     (certificate.system or {}).get("outputs") or [])) if r.output_range
                          else None, "not bounded"),
                 Quantity("Outward speed on the boundary", r.margin, "not proved",
                          bound="upper"),
                 Quantity("Witness (flow leaves R)", r.witness, "none"),
                 Quantity("Simulated attractor", r.attractor or None, "not simulated"),
                 Quantity("Its box (simulated)", att, "none"),
                 Quantity("It leaves X", r.attractor_leaves_box),
                 Quantity("A box that holds it", suggest, "not needed"),
                 Quantity("Regions tried", len(r.candidates)))
        numbers = (Quantity("region", what), Quantity("region lies in", hull, "not bounded"),
                   Quantity("outward speed bound", r.margin, "not proved", sig=6,
                            bound="upper"),
                   Quantity("attractor box (simulated)", att, "none"),
                   Quantity("attractor leaves X", r.attractor_leaves_box),
                   Quantity("suggested box", suggest, "not needed"),
                   Quantity("regions tried", len(r.candidates)))
        settings = certificate.settings or {}
        return Presentation(
            sampled=Quantity("attractor leaves X (simulated)", r.attractor_leaves_box),
            proved=Quantity("invariant region", what if r.status == Status.PROVED else None,
                            "none proved"),
            setting=(setting_quantity("invariance_boxes", settings),),
            numbers=numbers, facts=facts)


CHECK = InvarianceCheck()
