"""The gain network k(xhat, y): an MLP with a C^1 activation plus a linear injection term.

`GainNetwork` is an MLP on concat(xhat, y) (activation from `certify.model.activations`, default
tanh) plus an optional constant output-injection term. Two structures:

- ``direct``:     k = N(xhat, y)                          + K (y - h(xhat))
- ``structural``: k = G(xhat, y) (y - h(xhat))            + K (y - h(xhat)),  G = N reshaped
  to n x p, so that k(x, h(x)) = 0 by construction.

`K` (n x p, default zero) carries a linear observer gain (the certified LMI baseline, or a
warm start). `spec()` gives the `certify.model.gain.GainSpec` every evaluation goes through
(`certify.model.gain.propagate`); this module only owns the parameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from certify.model import activations
from certify.model.gain import ROWS, GainSpec, propagate
from certify.model.gain.spec import STRUCTURES

__all__ = ["GainNetwork", "STRUCTURES"]


class GainNetwork(nn.Module):
    """MLP on concat(xhat, y) with a C^1 activation and a linear injection buffer `K`."""

    def __init__(self, n: int, p: int, hidden: Sequence[int] = (30,) * 5,
                 structure: str = "direct", K: torch.Tensor | None = None,
                 activation: str = activations.DEFAULT) -> None:
        super().__init__()
        if structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}; got {structure!r}")
        if n < 1 or p < 1 or any(int(h) < 1 for h in hidden):
            raise ValueError("n, p and every hidden width must be >= 1")
        self.act = activations.get(activation)  # ValueError for non-C^1 / unknown names
        self.activation = self.act.name
        self.n, self.p = int(n), int(p)
        self.hidden = [int(h) for h in hidden]
        self.structure = structure
        widths = [self.n + self.p, *self.hidden, self.out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        K0 = torch.zeros(self.n, self.p) if K is None else torch.as_tensor(K).clone()
        self.register_buffer("K", K0.to(self.layers[0].weight.dtype))

    @property
    def out_dim(self) -> int:
        return self.n if self.structure == "direct" else self.n * self.p

    def architecture(self) -> dict[str, Any]:
        """Plain-data description stored in checkpoints."""
        return {"n": self.n, "p": self.p, "hidden": list(self.hidden),
                "activation": self.activation, "structure": self.structure}

    @classmethod
    def from_architecture(cls, arch: dict[str, Any]) -> GainNetwork:
        """The network an `architecture()` describes (no "activation" key: tanh, as in
        checkpoints written before activations were selectable)."""
        return cls(arch["n"], arch["p"], arch["hidden"], arch.get("structure", "direct"),
                   activation=arch.get("activation", activations.DEFAULT))

    def weights(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(W, b)] per layer, W of shape [out, in], for `certify.enclose` (the prover),
        which reads the activation's enclosures and relaxations from `act`."""
        return self.layer_weights()

    def layer_weights(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(W, b)] per layer, W of shape [out, in] (any activation)."""
        return [(layer.weight, layer.bias) for layer in self.layers]

    def spec(self, dtype: torch.dtype | None = None, detach: bool = False) -> GainSpec:
        """The gain's description over this network's parameters (cast to `dtype` if given)."""
        s = GainSpec(self.n, self.p, tuple(self.layer_weights()), self.act, self.structure,
                     self.K)
        return s if dtype is None and not detach else s.to(dtype or s.dtype, detach=detach)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """N(z) for z = concat(xhat, y) of shape [B, n+p] -> [B, out_dim]."""
        return propagate(self.spec(), ROWS, z, 0).value

    def forward_with_jacobian(self, z: torch.Tensor, columns: int | None = None
                              ) -> tuple[torch.Tensor, torch.Tensor]:
        """N(z) [B, out] and dN/dz[:, :, :columns] [B, out, columns], in forward mode."""
        m = z.shape[1] if columns is None else int(columns)
        out = propagate(self.spec(), ROWS, z, m)
        return out.value, out.jac
