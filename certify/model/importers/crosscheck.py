"""The import check: the imported network against the model itself, before anything is certified.

Reading a graph is pattern matching, and a pattern read wrongly certifies a different function.
So every import ends here: the model file is evaluated by its own runtime (`Reference`:
onnxruntime or onnx's reference evaluator for ONNX, torch for TorchScript and state_dicts) at
points of the spec's box X x Y and a few outside it, and the imported `GainNetwork` (the network
that will be certified, float64) must give the same values N(z) and Jacobians dN/dz there. A
difference is a `ModelImportError` (exit 2) naming the first layer whose output u = W h + b
differs from the model's tensor (where the runtime can show intermediate tensors), else saying
by how much values or Jacobians differ and where.

Tolerance, honestly: the model computes in its own precision (unit roundoff u: 2^-53 for
float64, 2^-24 for float32), so the two evaluations may differ by rounding alone. The allowance
is a first-order bound of that rounding, propagated through the imported layers at each point:
for u = W h + b, gamma(k) = k u / (1 - k u) times |W| |h| + |b| (k the dot product's length), plus
|W| times the input's own error; each activation adds C_ACT u (1 + |u| + |h|) (libm and runtime
kernels are a few ulps) and passes on its input's error with its Lipschitz constant;
Jacobians are bounded the same way through |W| and the activation's derivative (|f''| <= 1 for
every supported activation), all times SAFETY. In float64 this is about 1e-14 of the magnitudes
|W| |h| + |b| the layers add up, in float32 about 1e-5 of them: far below any misreading, which
changes the output by a whole term (an operand swapped, a bias dropped, an activation added),
and it is not loosened by the output's size (a cancelling output is judged against the
magnitudes of what cancels). Known, documented differences between the model and the network
certified are added where the reader found them (`Deviation`): torch's softplus returns u above
its threshold t (at most log(1 + e^-t) in value, sigmoid(-t) in slope), and an erf-form GELU
written with float32 roundings of its constants (relative deviation d: d (1 + |u|)).

ONNX runtimes give values only, so an ONNX model's Jacobian is its fourth-order central finite
difference (steps u^(1/5) over the first layer's column scale), compared with the imported
network's Jacobian within the difference's own error: its truncation (measured on the imported
network with the same stencil) plus 1.5 times the value allowance over the step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from certify.model.importers.result import ImportedModel, Layer, ModelImportError

#: ulps allowed per activation evaluation (libm, onnxruntime's kernels), times (1 + |u| + |h|)
C_ACT = 16.0
#: the rounding bound is first order and assumes the worst sign in every sum: times this
SAFETY = 4.0
#: bound on |f''| of every supported activation (tanh 0.77, gelu 0.80, silu 0.5, elu 1, ...)
SECOND_DERIVATIVE_BOUND = 1.0
POINTS_INSIDE = 48
POINTS_OUTSIDE = 16
SEED = 20240528


@dataclass(frozen=True)
class Deviation:
    """Known differences between the model's activation and the exact one certified: absolute
    in value and in slope, and relative (times 1 + |u|) in both."""

    value: float = 0.0
    slope: float = 0.0
    relative: float = 0.0


class Reference(Protocol):
    """The model itself, evaluated by its own runtime.

    `what` names the runtime (for notes and messages); `dtype` is the precision the model
    computes in; `deviation` what its activation may differ by from the exact one (a
    `Deviation`). `values(z)` takes points z [B, n+p] (float64, already representable in
    `dtype`) and returns N(z) [B, out] as float64; `jacobians(z)` returns dN/dz [B, out, n+p]
    or None when the runtime has no derivatives; `tensors(z, names)` returns the model's
    intermediate tensors by name ([B, width] each) or None when it cannot show them.
    """

    what: str
    dtype: np.dtype
    deviation: Deviation

    def values(self, z: np.ndarray) -> np.ndarray: ...

    def jacobians(self, z: np.ndarray) -> np.ndarray | None: ...

    def tensors(self, z: np.ndarray, names: Sequence[str]) -> dict[str, np.ndarray] | None: ...


def sample_points(box: np.ndarray | None, m: int, dtype: np.dtype) -> np.ndarray:
    """Points [B, m]: POINTS_INSIDE uniform in the box (its centre first), POINTS_OUTSIDE at
    1.2 to 3 half-widths from the centre; without a box, [-2, 2]^m. Rounded to `dtype` (the
    model reads its input in its own precision), returned as float64. Deterministic."""
    if box is None:
        box = np.tile([-2.0, 2.0], (m, 1))
    box = np.asarray(box, dtype=np.float64)
    lo, hi = box[:, 0], box[:, 1]
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    half = np.where(half > 0, half, np.maximum(1e-3 * (1 + np.abs(centre)), 1e-3))
    rng = np.random.default_rng(SEED)
    inside = centre + half * rng.uniform(-1, 1, size=(POINTS_INSIDE, m))
    inside[0] = centre
    signs = rng.choice([-1.0, 1.0], size=(POINTS_OUTSIDE, m))
    outside = centre + half * signs * rng.uniform(1.2, 3.0, size=(POINTS_OUTSIDE, m))
    z = np.concatenate([inside, outside])
    return z.astype(dtype).astype(np.float64)


# ----- the rounding allowance -----------------------------------------------------------------
@dataclass
class Bounds:
    """The imported network evaluated with its rounding allowance at points z [B, m]."""

    pre: list[np.ndarray]  # u = W h + b of each layer [B, width], float64
    pre_tol: list[np.ndarray]  # the allowance on each u
    value_tol: np.ndarray  # [B, out]
    jac_tol: np.ndarray | None  # [B, out, m] (None when not asked for)


def _gamma(k: int, unit: float) -> float:
    """k u / (1 - k u): the relative error bound of a k-term sum; meaningless once k u ~ 1."""
    if k * unit >= 0.5:
        raise ModelImportError(f"a layer sums {k} terms in a precision of {unit:.1g}: too "
                               "imprecise for its rounding to be bounded (export in float32 or "
                               "float64)")
    return k * unit / (1 - k * unit)


def rounding_bounds(layers: Sequence[Layer], activation: str, z: np.ndarray, unit: float,
                    deviation: Deviation, jacobians: bool = True) -> Bounds:
    """The layers' pre-activations at z and the allowance on them, on N(z) and (if asked) on
    dN/dz, for a model computing in unit roundoff `unit` (see the module docstring)."""
    import torch

    from certify.model.activations import get

    act = get(activation)
    U = unit + np.finfo(np.float64).eps / 2  # the model's rounding and the network's own
    B, m = z.shape
    h, mh, eh = z, np.abs(z), np.zeros_like(z)
    MJh = np.broadcast_to(np.eye(m), (B, m, m)) if jacobians else None
    eJh = np.zeros((B, m, m)) if jacobians else None
    MJu = eJu = None
    pre, pre_tol = [], []
    for index, layer in enumerate(layers):
        W, b = layer.W, layer.b
        absW = np.abs(W)
        if layer.fold is not None:  # the model computes W0 (s z + t) + b0
            W0, b0, s, t = layer.fold
            mzn = np.abs(z * s) + np.abs(t)
            mu = mzn @ np.abs(W0).T + np.abs(b0)
            eu = _gamma(W.shape[1] + 3, U) * mu
            if jacobians:
                MJu = np.broadcast_to(absW, (B, *W.shape))
                eJu = _gamma(2, U) * MJu
        else:
            mu = mh @ absW.T + np.abs(b)
            eu = _gamma(W.shape[1] + 1, U) * mu + eh @ absW.T
            if jacobians:
                MJu = np.einsum("oi,bim->bom", absW, MJh)
                eJu = _gamma(W.shape[1], U) * MJu + np.einsum("oi,bim->bom", absW, eJh)
        u = h @ W.T + b
        pre.append(u)
        pre_tol.append(SAFETY * eu)
        if index == len(layers) - 1:
            tiny = 64 * np.finfo(np.float64).tiny
            return Bounds(pre, pre_tol, SAFETY * eu + tiny,
                          SAFETY * eJu + tiny if jacobians else None)
        ut = torch.from_numpy(u)
        f, d = (x.numpy() for x in act.f_and_d1(ut))
        au = np.abs(u)
        e_act = C_ACT * U * (1 + au + np.abs(f)) + deviation.value + deviation.relative * (1 + au)
        ed = (SECOND_DERIVATIVE_BOUND * eu + C_ACT * U * (1 + au) + deviation.slope
              + deviation.relative * (1 + au))
        eh = act.lipschitz * eu + e_act
        if jacobians:
            ad = np.abs(d)[..., None]
            eJh = ed[..., None] * (MJu + eJu) + ad * eJu + U * ad * MJu
            MJh = ad * MJu + eJh
        h, mh = f, np.abs(f) + eh
    raise ModelImportError("no layers to check")  # unreachable: finish() refuses no layers


def _joined(a: Bounds, b: Bounds) -> Bounds:
    """The value parts of two `Bounds`, one after the other (no Jacobians)."""
    return Bounds([np.concatenate(x) for x in zip(a.pre, b.pre)],
                  [np.concatenate(x) for x in zip(a.pre_tol, b.pre_tol)],
                  np.concatenate([a.value_tol, b.value_tol]), None)


# ----- the check ------------------------------------------------------------------------------
def _point(z: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in z) + ")"


def _imported(model: ImportedModel, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import torch

    with torch.no_grad():
        value, jac = model.network().forward_with_jacobian(torch.from_numpy(z))
    return value.numpy(), jac.numpy()


def _evaluate(reference: Reference, method: str, *args: Any) -> Any:
    """A call into the model's runtime; its failure is the model's (exit 2), named."""
    try:
        return getattr(reference, method)(*args)
    except ModelImportError:
        raise
    except Exception as exc:  # runtimes raise their own types; any failure is the file's
        text = str(exc).strip().splitlines()
        detail = f": {text[0][:160]}" if text else ""
        raise ModelImportError(f"the model cannot be evaluated by {reference.what} to check the "
                               f"import ({type(exc).__name__}{detail})") from None


def _shape(values: Any, B: int, out: int, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size != B * out:
        raise ModelImportError(f"the model's {what} has {arr.size // max(B, 1)} values per point "
                               f"but the imported network has {out}")
    return arr.reshape(B, out)


def _locate(model: ImportedModel, reference: Reference, z: np.ndarray, bounds: Bounds
            ) -> str | None:
    """The first layer whose u differs from the model's tensor at the points z (or None)."""
    names = [layer.tensor for layer in model.layers]
    if any(name is None for name in names):
        return None
    try:
        tensors = reference.tensors(z, names)
    except Exception:  # only a diagnosis: the mismatch itself is reported either way
        return None
    if not tensors:
        return None
    for layer, u, tol in zip(model.layers, bounds.pre, bounds.pre_tol):
        got = tensors.get(layer.tensor)
        if got is None:
            return None
        got = np.asarray(got, dtype=np.float64).reshape(u.shape[0], -1)
        if got.shape != u.shape:
            return f"{layer.where} (the model's tensor there has {got.shape[1]} values)"
        if not np.all(np.abs(got - u) <= tol):
            return layer.where
    return f"the model's output after {model.layers[-1].where}"


def _refuse(model: ImportedModel, where: str | None, what: str, diff: float, tol: float,
            z: np.ndarray) -> ModelImportError:
    at = f"{where}: " if where else ""
    return ModelImportError(
        f"{model.path}: {at}the imported network's {what} differ from the model's "
        f"({diff:.3g} where rounding allows {tol:.2g}, at z = {_point(z)}): the file was not "
        "read as the function it computes, so it is refused (please report it)")


def check_import(model: ImportedModel, reference: Reference, box: np.ndarray | None) -> str:
    """Refuse `model` (ModelImportError) unless it equals the model file's own evaluation in
    values and Jacobians at sample points of `box` ([n+p, 2], or None) and around it; returns a
    note saying what was checked."""
    dtype, deviation = np.dtype(reference.dtype), reference.deviation
    unit = float(np.finfo(dtype).eps) / 2
    m = model.n + model.p
    z = sample_points(box, m, dtype)
    B, out = z.shape[0], model.layers[-1].W.shape[0]
    jac_model = _evaluate(reference, "jacobians", z)
    stencil = None
    if jac_model is None:  # values only: a central difference at each point, evaluated at once
        col = np.max(np.abs(model.layers[0].W), axis=0)
        step = unit ** 0.2 / np.maximum(1.0, col)
        offsets = np.array([1.0, -1.0, 2.0, -2.0])
        pts = (z[:, None, None, :] + offsets[None, None, :, None]
               * (np.eye(m) * step)[None, :, None, :])
        stencil = pts.reshape(-1, m).astype(dtype).astype(np.float64)
        points = np.concatenate([z, stencil])
    else:
        points = z
    value_model = _shape(_evaluate(reference, "values", points), len(points), out, "output")
    value_imp, jac_imp = _imported(model, points)
    at_z = rounding_bounds(model.layers, model.activation, z, unit, deviation)
    bounds = at_z if stencil is None else _joined(at_z, rounding_bounds(
        model.layers, model.activation, stencil, unit, deviation, jacobians=False))
    diff = np.abs(value_model - value_imp)
    bad = ~(diff <= bounds.value_tol)  # NaN in the model's output counts as a difference
    if bad.any():
        ratio = np.where(np.isfinite(diff), diff / bounds.value_tol, np.inf)
        row = int(np.argmax(np.max(ratio, axis=1)))
        col_ = int(np.argmax(ratio[row]))
        where = _locate(model, reference, points[row:row + 1], Bounds(
            [u[row:row + 1] for u in bounds.pre], [t[row:row + 1] for t in bounds.pre_tol],
            bounds.value_tol[row:row + 1], None))
        raise _refuse(model, where, "values", float(diff[row, col_]),
                      float(bounds.value_tol[row, col_]), points[row])
    worst_value = float(np.max(diff / bounds.value_tol))
    if stencil is None:
        jac_model = np.asarray(jac_model, dtype=np.float64).reshape(B, out, m)
        jac_tol = at_z.jac_tol
        jac_ref, jac_own = jac_model, jac_imp
    else:
        def central(values: np.ndarray) -> np.ndarray:  # [B*m*4, out] -> [B, out, m]
            v = values[B:].reshape(B, m, 4, out)
            d = 8 * (v[:, :, 0] - v[:, :, 1]) - (v[:, :, 2] - v[:, :, 3])
            return np.transpose(d / (12 * step[None, :, None]), (0, 2, 1))

        jac_ref, jac_own = central(value_model), jac_imp[:B]
        truncation = np.abs(jac_own - central(value_imp))
        tol_v = bounds.value_tol[B:].reshape(B, m, 4, out).max(axis=2)  # [B, m, out]
        rounding = 1.5 * np.transpose(tol_v, (0, 2, 1)) / step[None, None, :]
        jac_tol = 2 * truncation + rounding + at_z.jac_tol
    jdiff = np.abs(jac_ref - jac_own)
    bad = ~(jdiff <= jac_tol)
    if bad.any():
        ratio = np.where(np.isfinite(jdiff), jdiff / jac_tol, np.inf)
        row = int(np.argmax(ratio.reshape(B, -1).max(axis=1)))
        flat = int(np.argmax(ratio[row]))
        i, j = divmod(flat, m)
        raise _refuse(model, None, f"Jacobians (entry [{i}, {j}]; the values agree)",
                      float(jdiff[row, i, j]), float(jac_tol[row, i, j]), z[row])
    worst_jac = float(np.max(jdiff / jac_tol))
    how = "finite differences of its values" if stencil is not None else "autograd"
    return (f"checked against the model itself ({reference.what}, {dtype.name}) at {B} points "
            f"in and around the box: values and Jacobians ({how}) agree, the largest "
            f"difference {max(worst_value, worst_jac):.1g} of the rounding allowance")
