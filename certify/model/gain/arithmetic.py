"""Arithmetics for `certify.model.gain.propagate`: the number kind and the memory layout.

An arithmetic implements the primitives `propagate` and `compose` call (the `Arithmetic`
protocol below). Point implementations here, for float32 or float64 (the dtype of the spec
and the input decide):

- `RowArithmetic`: points in rows; value and tangent rows stacked as [B, 1 + m (+ J m), width]
  so each layer is one matrix product; differentiable (autograd reaches the weights).
- `ColumnArithmetic`: points in columns (feature-major [width, B] and [width, m, B]): every
  layer is one large product with contiguous elementwise passes; for dense no-grad grids.

`certify.model.gain.buffered.ChunkArithmetic` writes into a training chunk's preallocated buffers;
`certify.model.gain.interval.IntervalArithmetic` and `certify.model.gain.taylor.TaylorArithmetic`
implement the same protocol over intervals and first-order Taylor models.
"""

from __future__ import annotations

from typing import Any, Protocol

import torch

from certify.model.activations import Activation
from certify.model.gain.propagate import NetOutput


class Arithmetic(Protocol):
    """What `propagate` (first block) and `compose` (second block) need from a number kind.

    Shapes are given in the standard (row) layout; an arithmetic may store its values in any
    layout as long as `output` returns N [B, out], dN/dz [B, out, m], d2N [B, out, J, m].
    """

    def input_layer(self, z: Any, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[Any, Any]:
        """pre = W z + b [B, h] and its z-derivatives T = W[:, :m] ([B, m, h]; None if m = 0)."""

    def zero_second(self, pre: Any, J: int, m: int) -> Any:
        """Second derivatives of the first pre-activation: zero, [B, J m, h]."""

    def activate(self, act: Activation, pre: Any, layer: int, order: int
                 ) -> tuple[Any, Any, Any]:
        """(f(pre), f'(pre), f''(pre) or None when order < 2), elementwise [B, h]."""

    def scale(self, s: Any, T: Any, layer: int) -> Any:
        """s * T: the per-neuron factor [B, h] applied to every tangent [B, m, h]."""

    def second(self, s2: Any, T: Any, s: Any, S: Any, J: int, layer: int) -> Any:
        """s2 * T_j T_m + s * S_jm for j < J (second-order chain rule), [B, J m, h]."""

    def affine(self, a: Any, T: Any, S: Any, W: torch.Tensor, b: torch.Tensor, layer: int
               ) -> tuple[Any, Any, Any]:
        """(W a + b, W T, W S): the bias enters the value only."""

    def output(self, pre: Any, T: Any, S: Any) -> NetOutput:
        """The result in the standard layout."""

    # --- composition with the injection (see `compose`) ---
    def cols(self, x: Any, start: int, stop: int) -> Any: ...
    def reshape_out(self, out: Any, n: int, p: int) -> Any: ...
    def reshape_jac(self, jac: Any, n: int, p: int) -> Any: ...
    def matvec(self, A: Any, v: Any) -> Any: ...
    def contract(self, dA: Any, v: Any) -> Any: ...
    def matmul(self, A: Any, B: Any) -> Any: ...
    def add(self, a: Any, b: Any) -> Any: ...
    def sub(self, a: Any, b: Any) -> Any: ...
    def const_matvec(self, K: torch.Tensor, v: Any) -> Any: ...
    def const_matmul(self, K: torch.Tensor, A: Any) -> Any: ...
    def add_const(self, a: Any, K: torch.Tensor) -> Any: ...

    # --- second derivatives of the composition (see `compose_second`) ---
    def reshape(self, x: Any, shape: tuple[int, ...]) -> Any:
        """x [B, ...] viewed as [B, *shape]."""

    def index(self, x: Any, idx: tuple) -> Any:
        """x[idx] (slices and new axes; the batch dimension first)."""

    def mul(self, a: Any, b: Any) -> Any:
        """Elementwise product, broadcasting."""

    def sum(self, x: Any, dim: int) -> Any:
        """Sum over dimension `dim`."""


class PointCompose:
    """`compose` primitives on point tensors in the row layout."""

    def inputs(self, xhat: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The network's input z = (xhat, y) [B, n + p]."""
        return torch.cat([xhat, y], dim=1)

    def cols(self, x: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        return x[..., start:stop]

    def reshape_out(self, out: torch.Tensor, n: int, p: int) -> torch.Tensor:
        return out.reshape(out.shape[0], n, p)

    def reshape_jac(self, jac: torch.Tensor, n: int, p: int) -> torch.Tensor:
        return jac.reshape(jac.shape[0], n, p, jac.shape[-1])

    def matvec(self, A: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return torch.einsum("bij,bj->bi", A, v)

    def contract(self, dA: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return torch.einsum("bijm,bj->bim", dA, v)

    def matmul(self, A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
        return A @ B

    def add(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a + b

    def sub(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a - b

    def const_matvec(self, K: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return v @ K.T

    def const_matmul(self, K: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
        return K @ A

    def add_const(self, a: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        return a + K

    def reshape(self, x: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
        return x.reshape(x.shape[0], *shape)

    def index(self, x: torch.Tensor, idx: tuple) -> torch.Tensor:
        return x[idx]

    def mul(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a * b

    def sum(self, x: torch.Tensor, dim: int) -> torch.Tensor:
        return x.sum(dim)


class RowArithmetic(PointCompose):
    """Points in rows: value and derivative rows travel as one tensor [B, rows, width]."""

    def input_layer(self, z: torch.Tensor, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        pre = z @ W.T + b
        T = W[:, :m].T.unsqueeze(0).expand(z.shape[0], m, W.shape[0]) if m else None
        return pre, T

    def zero_second(self, pre: torch.Tensor, J: int, m: int) -> torch.Tensor:
        return pre.new_zeros(pre.shape[0], J * m, pre.shape[1])

    def activate(self, act: Activation, pre: torch.Tensor, layer: int, order: int
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        a, s = act.f_and_d1(pre)
        return a, s, (act.d2_given(pre, a, s) if order >= 2 else None)

    def scale(self, s: torch.Tensor, T: torch.Tensor, layer: int) -> torch.Tensor:
        return s.unsqueeze(1) * T

    def second(self, s2: torch.Tensor, T: torch.Tensor, s: torch.Tensor, S: torch.Tensor,
               J: int, layer: int) -> torch.Tensor:
        B, m, h = T.shape
        TT = T[:, :J, None, :] * T[:, None, :, :]  # [B, J, m, h]
        out = s2[:, None, None, :] * TT + s[:, None, None, :] * S.view(B, J, m, h)
        return out.reshape(B, J * m, h)

    def affine(self, a: torch.Tensor, T: torch.Tensor | None, S: torch.Tensor | None,
               W: torch.Tensor, b: torch.Tensor, layer: int
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        if T is None and S is None:
            return torch.addmm(b, a, W.T), None, None
        parts = [a.unsqueeze(1)] + [x for x in (T, S) if x is not None]
        A = torch.cat(parts, dim=1)  # [B, rows, h]
        Z = (A.reshape(-1, A.shape[-1]) @ W.T).reshape(A.shape[0], A.shape[1], -1)
        m = 0 if T is None else T.shape[1]
        return Z[:, 0] + b, (Z[:, 1:1 + m] if T is not None else None), \
            (Z[:, 1 + m:] if S is not None else None)

    def output(self, pre: torch.Tensor, T: torch.Tensor | None, S: torch.Tensor | None
               ) -> NetOutput:
        jac = None if T is None else T.transpose(1, 2)
        hess = None
        if S is not None:
            B, out = pre.shape
            m = T.shape[1]
            J = S.shape[1] // m
            hess = S.reshape(B, J, m, out).permute(0, 3, 1, 2)
        return NetOutput(pre, jac, hess)


class ColumnArithmetic(PointCompose):
    """Points in columns (feature-major), first order, for no-grad dense grids."""

    def input_layer(self, z: torch.Tensor, W: torch.Tensor, b: torch.Tensor, m: int
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        pre = torch.addmm(b[:, None], W, z.T)  # [h, B]
        T = W[:, :m, None].expand(-1, m, z.shape[0]) if m else None  # [h, m, B]
        return pre, T

    def activate(self, act: Activation, pre: torch.Tensor, layer: int, order: int
                 ) -> tuple[torch.Tensor, torch.Tensor, None]:
        if order >= 2:
            raise ValueError("ColumnArithmetic propagates first derivatives only")
        a, s = act.f_and_d1(pre)
        return a, s, None

    def scale(self, s: torch.Tensor, T: torch.Tensor, layer: int) -> torch.Tensor:
        return T * s[:, None, :]

    def affine(self, a: torch.Tensor, T: torch.Tensor | None, S: None, W: torch.Tensor,
               b: torch.Tensor, layer: int) -> tuple[torch.Tensor, torch.Tensor | None, None]:
        if T is not None:
            h, m, B = T.shape
            T = torch.mm(W, T.reshape(h, m * B)).view(W.shape[0], m, B)  # all tangents at once
        return torch.addmm(b[:, None], W, a), T, None

    def output(self, pre: torch.Tensor, T: torch.Tensor | None, S: None) -> NetOutput:
        return NetOutput(pre.T, None if T is None else T.permute(2, 0, 1))


ROWS = RowArithmetic()
COLUMNS = ColumnArithmetic()
