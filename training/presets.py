"""Training settings: one frozen dataclass, its constraints beside it, and named presets.

`paper` reproduces the source method (METHOD.md section 2): 4000 uniform collocation points,
5 x 30 tanh, Sylvester-minor MPDI loss with the sign fix, the BC loss, the loss weights of the
system spec's `[training.paper]` table, Adam lr 1e-3 x 500 full-batch, then L-BFGS lr 1 with a
strong Wolfe line search x 500. `tiny` is the same recipe, small enough for tests. Both leave
the verification-aware term (`curvature_weight`, `training.curvature`) off; `certified` turns
it on (`CERTIFIED_CURVATURE_WEIGHT`).

Errors are one line naming the field (and its flag): ``training: points (--points) must be an
int >= 1; got 0``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from certify.errors import CertifyError, SettingsError

if TYPE_CHECKING:
    from certify.spec.system import System

LOSS_KINDS = ("minors", "eigen", "eigen_squared")
DTYPES = ("float32", "float64")
#: the certified preset's weight of the Jacobian-variation term (`training.curvature`): the
#: choice behind it is `bench/curvature.py proof` (proof sub-boxes at the same verdict and L
#: against weights 0 and 1e-3)
CERTIFIED_CURVATURE_WEIGHT = 1e-2

# command-line flag of each field, for error messages
FLAGS = {
    "lam": "--lam", "P": "--metric", "seed": "--seed", "points": "--points",
    "hidden": "--hidden", "adam_iters": "--adam-iters", "lbfgs_iters": "--lbfgs-iters",
    "preset": "--preset", "activation": "--activation",
    "curvature_weight": "--curvature-weight", "curvature_radius": "--curvature-radius",
    "min_rate": "--min-rate", "verifier_weight": "--verifier-weight",
}


@dataclass(frozen=True)
class TrainConfig:
    """How a gain network is trained. `lam`/`P` of None mean "the system's design values"
    (`make_config` fills them in)."""

    preset: str = "paper"
    lam: float | None = None
    P: tuple[tuple[float, ...], ...] | None = None
    seed: int = 0
    points: int = 4000
    hidden: tuple[int, ...] = (30,) * 5
    adam_iters: int = 500
    adam_lr: float = 1e-3
    lbfgs_iters: int = 500
    lbfgs_lr: float = 1.0
    mu1: float = 1.0
    mu2: float = 1.0
    rho: tuple[float, ...] | None = None  # one weight per leading minor; None: all 1
    loss: str = "minors"
    margin: float = 0.0  # eigenvalue losses only: penalise lam_max(D) > -margin
    structure: str = "direct"
    dtype: str = "float32"
    activation: str = "tanh"  # a C^1 activation of certify.model.activations
    # verification-aware term (`training.curvature`): weight * mean relu(||J(z1) - J(z2)||_F^2
    # / r^2 - 0) over pairs of X x Y at normalised distance r = curvature_radius, J = dk/dxhat.
    # It keeps dk/dxhat nearly constant at the prover's sub-box scale, so the proof needs
    # fewer sub-boxes. 0 (off) in `paper`, which reproduces the source method as published.
    curvature_weight: float = 0.0
    curvature_radius: float = 0.02
    # training for the verifier (`training.verifier`; every preset that trains a network): weight *
    # the surrogate of the prover's box bound on sampled sub-boxes; 0 (off) in `paper`
    verifier_weight: float = 0.0

    def __post_init__(self) -> None:
        validate(self)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (lists, numbers, strings) for checkpoints and reports."""
        out = dataclasses.asdict(self)
        for key in ("P", "hidden", "rho"):
            if out[key] is not None:
                out[key] = [list(r) if isinstance(r, tuple) else r for r in out[key]]
        return out


def _fail(name: str, need: str, value: Any) -> SettingsError:
    flag = f" ({FLAGS[name]})" if name in FLAGS else ""
    return SettingsError(f"training: {name}{flag} must be {need}; got {value!r}")


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def validate(c: TrainConfig) -> None:
    """Check every field against its constraint; raise one `SettingsError` line."""
    # here, not at the top: they import torch, which `certify train --help` does not need
    from certify.model import activations
    from certify.model.network import STRUCTURES
    from certify.spec.system import MAX_LAM, validate_metric

    if not isinstance(c.preset, str) or not c.preset:
        raise _fail("preset", "a preset name", c.preset)
    for name, lo in (("seed", 0), ("points", 1), ("adam_iters", 0), ("lbfgs_iters", 0)):
        v = getattr(c, name)
        if not _is_int(v) or v < lo:
            raise _fail(name, f"an int >= {lo}", v)
    for name in ("adam_lr", "lbfgs_lr"):
        v = getattr(c, name)
        if not _is_real(v) or v <= 0:
            raise _fail(name, "a finite number > 0", v)
    if not _is_real(c.curvature_radius) or not 0 < c.curvature_radius < 0.5:
        raise _fail("curvature_radius", "a number in (0, 0.5) (a fraction of each box side)",
                    c.curvature_radius)
    for name in ("mu1", "mu2", "margin", "curvature_weight", "verifier_weight"):
        v = getattr(c, name)
        if not _is_real(v) or v < 0:
            raise _fail(name, "a finite number >= 0", v)
    if c.lam is not None and (not _is_real(c.lam) or not 0 < c.lam <= MAX_LAM):
        raise _fail("lam", f"a finite number in (0, {MAX_LAM:g}]", c.lam)
    if (not isinstance(c.hidden, tuple) or not c.hidden
            or any(not _is_int(h) or h < 1 for h in c.hidden)):
        raise _fail("hidden", "a non-empty list of positive layer widths, like 30,30,30",
                    c.hidden)
    if c.rho is not None and (not isinstance(c.rho, tuple) or not c.rho
                              or any(not _is_real(r) or r < 0 for r in c.rho)):
        raise _fail("rho", "a list of finite numbers >= 0 (one per leading minor)", c.rho)
    if c.P is not None:
        ok = isinstance(c.P, tuple) and all(isinstance(r, tuple) for r in c.P)
        if not ok:
            raise _fail("P", "a square matrix like [[1, 0], [0, 1]]", c.P)
        try:
            validate_metric(np.asarray(c.P, dtype=float), len(c.P), "training")
        except (CertifyError, ValueError) as exc:
            msg = str(exc).replace("training: ", "", 1)
            raise SettingsError(f"training: P (--metric): {msg}; got {c.P!r}") from None
    if c.loss not in LOSS_KINDS:
        raise _fail("loss", f"one of {list(LOSS_KINDS)}", c.loss)
    if c.structure not in STRUCTURES:
        raise _fail("structure", f"one of {list(STRUCTURES)}", c.structure)
    if c.dtype not in DTYPES:
        raise _fail("dtype", f"one of {list(DTYPES)}", c.dtype)
    if not isinstance(c.activation, str):
        raise _fail("activation", f"one of {activations.names()}", c.activation)
    try:
        activations.get(c.activation)
    except ValueError as exc:
        raise SettingsError(f"training: activation (--activation): {exc}") from None


def check_for_system(c: TrainConfig, system: System) -> None:
    """The constraints that depend on the system: P is n x n, rho has n weights."""
    if c.P is not None and len(c.P) != system.n:
        raise _fail("P", f"a {system.n}x{system.n} matrix for system {system.name}",
                    [list(r) for r in c.P])
    if c.rho is not None and len(c.rho) != system.n:
        raise _fail("rho", f"{system.n} weights (one per leading minor of the "
                    f"{system.n}x{system.n} matrix D)", list(c.rho))


def paper_weights(system: System) -> dict[str, Any]:
    """mu1, mu2, rho from the spec's `[training.paper]` table (all 1 where it is absent)."""
    table = system.training.get("paper", {}) if isinstance(system.training, dict) else {}
    where = f"system {system.name}: [training.paper]"
    if not isinstance(table, dict):
        raise SettingsError(f"{where} must be a table")
    out: dict[str, Any] = {}
    for key in ("mu1", "mu2"):
        v = table.get(key, 1.0)
        if not _is_real(v) or v < 0:
            raise SettingsError(f"{where} {key} must be a finite number >= 0; got {v!r}")
        out[key] = float(v)
    rho = table.get("rho", [1.0] * system.n)
    if (not isinstance(rho, list) or len(rho) != system.n
            or any(not _is_real(r) or r < 0 for r in rho)):
        raise SettingsError(f"{where} rho must be a list of {system.n} numbers >= 0; "
                            f"got {rho!r}")
    out["rho"] = tuple(float(r) for r in rho)
    return out


def _paper(system: System) -> dict[str, Any]:
    """the source method reproduced (the default): 4000 points, 5x30 tanh, Adam then L-BFGS

    The loss weights come from the spec's `[training.paper]` table."""
    return {"preset": "paper", **paper_weights(system)}


def _tiny(system: System) -> dict[str, Any]:
    """the paper recipe at toy size (200 points, 8x8, 30+30 iterations): a smoke test of a
    spec or a pipeline in seconds, not a gain to certify"""
    return {"preset": "tiny", **paper_weights(system), "points": 200, "hidden": (8, 8),
            "adam_iters": 30, "lbfgs_iters": 30}


def _certified(system: System) -> dict[str, Any]:
    """counterexample-guided training for a certificate: metric from the LMI, structural
    gain, proofs between rounds

    `training.certified`: structural gain (eps_bar = 0), eigenvalue loss with margin in the
    LMI metric, warm start from the LMI gain; adam_iters are Adam steps per CEGIS round,
    margin is lam_max(D) <= -margin."""
    return {"preset": "certified", "points": 4000, "hidden": (16, 16), "adam_iters": 300,
            "adam_lr": 1e-3, "lbfgs_iters": 0, "loss": "eigen", "margin": 0.2,
            "structure": "structural", "mu1": 1.0, "mu2": 0.0,
            "curvature_weight": CERTIFIED_CURVATURE_WEIGHT}


def _bound(system: System) -> dict[str, Any]:
    """a linear observer designed for the certified error bound (vertex SDP; rate free, or
    floored by --min-rate, or fixed by --lam), then a learned gain trained against the same
    certificate, returned only if it beats the linear design

    `training.bound`: adam_iters are Adam steps per round of the learned attempt (0: the
    linear design only); points, hidden, seed and activation are the learned attempt's."""
    return {"preset": "bound", "points": 2000, "hidden": (8, 8), "adam_iters": 150,
            "adam_lr": 1e-3, "lbfgs_iters": 0, "loss": "eigen", "structure": "structural",
            "mu1": 1.0, "mu2": 0.0}


# name -> function(system) giving the preset's field values; the first paragraph of each
# function's docstring is what `certify train --help` says of it (`preset_summary`)
PRESETS: dict[str, Callable[[System], dict[str, Any]]] = {"paper": _paper, "tiny": _tiny,
                                                          "certified": _certified,
                                                          "bound": _bound}


def preset_summary(name: str) -> str:
    """What preset `name` is, in one line (its function's docstring, first paragraph)."""
    doc = (PRESETS[name].__doc__ or "").strip().split("\n\n", 1)[0]
    return " ".join(doc.split())


def make_config(system: System, preset: str = "paper", **overrides: Any) -> TrainConfig:
    """The preset's settings for `system`, with `overrides` (None values ignored), validated;
    lam and P default to the system's design values."""
    if preset not in PRESETS:
        raise SettingsError(f"training: unknown preset {preset!r} (known: "
                            f"{', '.join(PRESETS)})")
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise SettingsError(f"training: unknown setting(s) {', '.join(unknown)} "
                            f"(known: {', '.join(sorted(fields))})")
    values = PRESETS[preset](system)
    values.update({k: v for k, v in overrides.items() if v is not None})
    for key in ("hidden", "rho"):
        if isinstance(values.get(key), list):
            values[key] = tuple(values[key])
    if isinstance(values.get("P"), (list, np.ndarray)):
        values["P"] = tuple(tuple(float(v) for v in row) for row in np.asarray(values["P"]))
    if isinstance(values.get("lam"), int) and not isinstance(values.get("lam"), bool):
        values["lam"] = float(values["lam"])
    values.setdefault("lam", None)
    if values["lam"] is None:
        values["lam"] = float(system.lam)
    if values.get("P") is None:
        values["P"] = tuple(tuple(float(v) for v in row) for row in system.P)
    config = TrainConfig(**values)
    check_for_system(config, system)
    return config
