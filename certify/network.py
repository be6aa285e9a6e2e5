"""The gain network k(xhat, y) and its batched forward-mode Jacobian.

`GainNetwork` is a tanh MLP on concat(xhat, y) plus an optional constant output-injection
term. Two structures:

- ``direct``:     k = N(xhat, y)                          + K (y - h(xhat))
- ``structural``: k = G(xhat, y) (y - h(xhat))            + K (y - h(xhat)),  G = N reshaped
  to n x p, so that k(x, h(x)) = 0 by construction.

`K` (n x p, default zero) carries a linear observer gain (the certified LMI baseline, or a
warm start). The composition with h lives in `certify.kernels`; this module knows only the
MLP.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

STRUCTURES = ("direct", "structural")


class GainNetwork(nn.Module):
    """tanh MLP on concat(xhat, y) with a linear injection buffer `K`."""

    def __init__(self, n: int, p: int, hidden: Sequence[int] = (30,) * 5,
                 structure: str = "direct", K: torch.Tensor | None = None) -> None:
        super().__init__()
        if structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}; got {structure!r}")
        if n < 1 or p < 1 or any(int(h) < 1 for h in hidden):
            raise ValueError("n, p and every hidden width must be >= 1")
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
        return {"n": self.n, "p": self.p, "hidden": list(self.hidden), "activation": "tanh",
                "structure": self.structure}

    @classmethod
    def from_architecture(cls, arch: dict[str, Any]) -> GainNetwork:
        return cls(arch["n"], arch["p"], arch["hidden"], arch.get("structure", "direct"))

    def weights(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """[(W, b)] per layer, W of shape [out, in]."""
        return [(layer.weight, layer.bias) for layer in self.layers]

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """N(z) for z = concat(xhat, y) of shape [B, n+p] -> [B, out_dim]."""
        a = z
        for layer in self.layers[:-1]:
            a = torch.tanh(layer(a))
        return self.layers[-1](a)

    def forward_with_jacobian(self, z: torch.Tensor, columns: int | None = None
                              ) -> tuple[torch.Tensor, torch.Tensor]:
        """N(z) [B, out] and dN/dz[:, :, :columns] [B, out, columns], in forward mode.

        Value and tangents travel together as rows of one tensor [B, 1+columns, width], so each
        layer is a single matrix product; no Python loop over points.
        """
        m = z.shape[1] if columns is None else int(columns)
        W0, b0 = self.layers[0].weight, self.layers[0].bias
        pre = z @ W0.T + b0  # [B, h]
        tang = W0[:, :m].T.unsqueeze(0).expand(z.shape[0], m, W0.shape[0])  # [B, m, h]
        for layer in self.layers[1:]:
            t = torch.tanh(pre)
            s = 1.0 - t * t
            A = torch.cat([t.unsqueeze(1), s.unsqueeze(1) * tang], dim=1)  # [B, 1+m, h]
            Z = (A.reshape(-1, A.shape[-1]) @ layer.weight.T).reshape(A.shape[0], m + 1, -1)
            pre = Z[:, 0] + layer.bias
            tang = Z[:, 1:]
        return pre, tang.transpose(1, 2)
