"""Activation functions of the gain network: one module each, one registry.

`get(name) -> Activation` and `names()`. Only C^1 activations are accepted: the contraction
matrix D contains the network's Jacobian, so a jump in f' (ReLU, leaky ReLU, hardtanh, ...)
makes D discontinuous, and Theorem 1 (METHOD.md) needs a C^1 gain. Such names are refused
with that reason; unknown names are refused with the supported list. The contract every
activation meets is `certify.model.activations.base.Activation`.
"""

from __future__ import annotations

from certify.model.activations.base import Activation, Critical, LinearBounds
from certify.model.activations.elu import ELU_
from certify.model.activations.gelu import GELU_
from certify.model.activations.sigmoid import SIGMOID
from certify.model.activations.silu import SILU
from certify.model.activations.softplus import SOFTPLUS
from certify.model.activations.tanh import TANH

__all__ = ["Activation", "Critical", "LinearBounds", "get", "names", "DEFAULT"]

DEFAULT = "tanh"
_REGISTRY: dict[str, Activation] = {a.name: a for a in (TANH, SIGMOID, SOFTPLUS, SILU, ELU_,
                                                         GELU_)}
_ALIASES = {"swish": "silu", "logistic": "sigmoid", "gelu_exact": "gelu"}
#: non-C^1 activations, refused with the reason (their derivative jumps)
NOT_C1 = {
    "relu": "its derivative jumps at 0",
    "relu6": "its derivative jumps at 0 and 6",
    "leaky_relu": "its derivative jumps at 0",
    "prelu": "its derivative jumps at 0",
    "rrelu": "its derivative jumps at 0",
    "hardtanh": "its derivative jumps at -1 and 1",
    "hardsigmoid": "its derivative jumps at -3 and 3",
    "hardswish": "its derivative jumps at -3 and 3",
    "selu": "its derivative jumps at 0 (scale * alpha != scale)",
    "elu_alpha": "ELU with alpha != 1 has a derivative jump at 0",
    "abs": "its derivative jumps at 0",
    "step": "it is discontinuous",
    "sign": "it is discontinuous",
    "threshold": "it is discontinuous",
    "gelu_tanh": "not supported (use the exact, erf-based gelu)",
}


def _key(name: str) -> str:
    k = str(name).strip().lower().replace("-", "_")
    k = {"leakyrelu": "leaky_relu", "hard_tanh": "hardtanh", "hard_sigmoid": "hardsigmoid",
         "hard_swish": "hardswish"}.get(k, k)
    return _ALIASES.get(k, k)


def names() -> list[str]:
    """The supported activation names, sorted."""
    return sorted(_REGISTRY)


def get(name: str) -> Activation:
    """The activation called `name` (case-insensitive; 'swish' is silu).

    Raises ValueError for a non-C^1 activation (saying why) or an unknown name (listing the
    supported ones).
    """
    key = _key(name)
    act = _REGISTRY.get(key)
    if act is not None:
        return act
    supported = ", ".join(names())
    if key in NOT_C1:
        raise ValueError(f"activation {name!r} is refused: {NOT_C1[key]}, so D would be "
                         f"discontinuous; Theorem 1 needs a C^1 gain (supported: {supported})")
    raise ValueError(f"unknown activation {name!r}; supported: {supported}")
