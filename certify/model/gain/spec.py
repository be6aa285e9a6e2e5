"""The description of the gain: MLP layers, activation, injection structure and K.

    direct:      k(xhat, y) = N(xhat, y)                     + K (y - h(xhat))
    structural:  k(xhat, y) = G(xhat, y) (y - h(xhat))       + K (y - h(xhat)),
                 G = N reshaped to [n, p], so k(x, h(x)) = 0 by construction,

N(z) = W_L a_{L-1} + b_L,  a_i = f(W_i a_{i-1} + b_i),  a_0 = z = concat(xhat, y).

A `GainSpec` holds references to the weights (no copy; `to(dtype)` casts differentiably), so
autograd through the propagation reaches the network's parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from certify.model.activations import Activation

STRUCTURES = ("direct", "structural")


@dataclass(frozen=True)
class GainSpec:
    """Everything that defines k(xhat, y) except the system's h."""

    n: int
    p: int
    layers: tuple[tuple[torch.Tensor, torch.Tensor], ...]  # (W [out, in], b [out]) per layer
    activation: Activation
    structure: str
    K: torch.Tensor  # [n, p]
    has_K: bool = field(init=False)

    def __post_init__(self) -> None:
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}; got {self.structure!r}")
        object.__setattr__(self, "has_K", bool(torch.any(self.K != 0)))

    @property
    def out_dim(self) -> int:
        """Width of N's output: n (direct) or n * p (structural)."""
        return self.n if self.structure == "direct" else self.n * self.p

    @property
    def structural(self) -> bool:
        return self.structure == "structural"

    @property
    def needs_h(self) -> bool:
        """Whether k depends on y - h(xhat) (structural, or a nonzero K)."""
        return self.structural or self.has_K

    @property
    def dtype(self) -> torch.dtype:
        return self.layers[0][0].dtype

    def to(self, dtype: torch.dtype, detach: bool = False) -> GainSpec:
        """The same gain with weights cast to `dtype` (contiguous; detached if asked)."""
        def cast(t: torch.Tensor) -> torch.Tensor:
            t = t.detach() if detach else t
            return t.to(dtype).contiguous()
        return GainSpec(self.n, self.p, tuple((cast(W), cast(b)) for W, b in self.layers),
                        self.activation, self.structure, cast(self.K))
