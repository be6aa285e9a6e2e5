"""The training loss heads through `certify.model.gain.compose` against frozen copies of the old
hand-composed heads (issue 11 item 3): same loss values and gradients, bit for bit, and a
seeded training run that ends on the same weights.

`_OldObjective._head` and `_OldCertObjective._head` are verbatim copies of the heads as they
were before the port (dk/dxhat = dG r - G Hx and dk/dy = dG_y r + G + K written by hand in
the chunk layout [m, N, out]); they are frozen here on purpose and must not be edited.
"""

from __future__ import annotations

import importlib

import pytest
import torch

from certify.model.kernels import sym
from certify.model.network import GainNetwork
from certify.spec.system import load_system
from training import losses
from training.cegis_objective import CertObjective
from training.collocation import collocation_points
from training.objective import Objective
from training.optim import Adam
from training.presets import make_config

# the module (the package `training` exports the function `train` under the same name)
train_module = importlib.import_module("training.train")


class _OldObjective(Objective):
    def _head(self, val, tan, k_bc, grad):  # frozen copy of the pre-port head
        n, p, N = self.n, self.p, self.N
        if self.structural:
            G = val.view(N, n, p)
            dG = tan.view(self.m, N, n, p)  # [j, b, i, q] = dG_iq/dxhat_j
            M = torch.einsum("jbiq,bq->bij", dG, self.r)
            if self.Hx is not None:
                M = M - G @ self.Hx
        else:
            M = tan.permute(1, 2, 0)  # [b, i, j] = dk_i/dxhat_j
        D = self.D0 + sym(M if self.P_is_identity else self.P @ M)
        bc = 0.0 if k_bc is None else float((k_bc * k_bc).sum())
        if self.loss == "minors":
            if grad:
                mpdi_t, gD = losses.minor_loss_sum_and_grad(D, self.weights.rho)
            else:
                mpdi_t, gD = losses.minor_loss(D, self.weights.rho, reduce="sum"), None
        else:
            squared = self.loss == "eigen_squared"
            if grad:
                Dl = D.detach().requires_grad_(True)
                with torch.enable_grad():
                    mpdi_t = losses.eigen_loss(Dl, self.margin, squared, reduce="sum")
                    (gD,) = torch.autograd.grad(mpdi_t, [Dl])
            else:
                mpdi_t, gD = losses.eigen_loss(D, self.margin, squared, reduce="sum"), None
        mpdi = float(mpdi_t)
        if not grad:
            return mpdi, bc, None
        scale = self.weights.mu1 / N
        gM = sym(gD) * scale
        if not self.P_is_identity:
            gM = self.P.T @ gM
        if self.structural:
            g_tan = torch.einsum("bij,bq->jbiq", gM, self.r).reshape(self.m, N, n * p)
            g_val = torch.zeros_like(val) if self.Hx is None else \
                (-(gM @ self.Hx.transpose(1, 2))).reshape(N, n * p)
            return mpdi, bc, [g_val, g_tan]
        g_tan = gM.permute(2, 0, 1)
        g_bc = k_bc * (2.0 * self.weights.mu2 / N)
        return mpdi, bc, [torch.zeros_like(val), g_tan, g_bc]


class _OldCertObjective(CertObjective):
    def _head(self, val, tan, k_bc, grad):  # frozen copy of the pre-port head
        n, p, N = self.n, self.p, self.N
        K_t = self.net.K.detach().to(val.dtype)
        val_l = val.detach().requires_grad_(grad)
        tan_l = tan.detach().requires_grad_(grad)
        kbc_l = None if k_bc is None else k_bc.detach().requires_grad_(grad)
        with torch.enable_grad():
            if self.structural:
                G = val_l.view(N, n, p)
                dG = tan_l.view(self.m, N, n, p)  # [j, b, i, q] = dG_iq / dz_j
                M = torch.einsum("jbiq,bq->bij", dG[:n], self.r)
                if self.Hx is not None:
                    M = M - G @ self.Hx
                dky = torch.einsum("jbiq,bq->bij", dG[n:], self.r) + G + K_t
            else:
                M = tan_l[:n].permute(1, 2, 0)
                dky = tan_l[n:].permute(1, 2, 0) + K_t
            D = self.D0 + sym(M if self.P_is_identity else self.P @ M)
            mpdi = losses.eigen_loss(D, self.margin, reduce="sum")
            total = self.mpdi_weight * mpdi / N
            lip = torch.zeros((), dtype=D.dtype)
            if self.lip_weight > 0:
                s = (dky * dky).sum(dim=(1, 2))
                q = self.lip_power
                scale = s.detach().max().clamp_min(1e-30)
                lip = torch.sqrt(scale) * ((s / scale) ** q).mean() ** (1.0 / (2.0 * q))
                total = total + self.lip_weight * lip
            bc = torch.zeros((), dtype=D.dtype)
            if kbc_l is not None:
                bc = (kbc_l * kbc_l).sum()
                total = total + self.weights.mu2 * bc / N
            self.last_lip = float(lip.detach())
            self.last_lip_max = float(torch.sqrt((dky * dky).sum(dim=(1, 2)).max()).detach())
            if not grad:
                return float(mpdi), float(bc), None
            inputs = [val_l, tan_l] + ([kbc_l] if kbc_l is not None else [])
            grads = torch.autograd.grad(total, inputs, allow_unused=True)
        grads = [torch.zeros_like(x) if g is None else g for x, g in zip(inputs, grads)]
        return float(mpdi), float(bc), grads


def _net(system, structure, with_K, seed=1):
    torch.manual_seed(seed)
    net = GainNetwork(system.n, system.p, (7, 6), structure=structure).float()
    if with_K:
        net.K.copy_(torch.randn(system.n, system.p))
    for prm in net.parameters():
        prm.requires_grad_(True)
    return net


def _grads(obj):
    values = obj.evaluate(grad=True)
    obj.close()
    return values, [prm.grad.clone() for prm in obj.params]


CASES = [("vdp", "direct", False, "minors", True), ("vdp", "direct", True, "eigen", False),
         ("vdp", "structural", True, "minors", False),
         ("vdp", "structural", False, "eigen_squared", True),
         ("three", "direct", True, "minors", False),
         ("three", "structural", True, "eigen", False)]


@pytest.mark.parametrize("which,structure,with_K,kind,identity", CASES)
def test_objective_head_is_the_old_head_bit_for_bit(system3, which, structure, with_K, kind,
                                                    identity):
    system = load_system("vdp") if which == "vdp" else system3
    x, y = collocation_points(system, 45, 3)
    P = torch.eye(system.n, dtype=torch.float64) if identity else \
        torch.as_tensor(system.P) + 0.2 * torch.eye(system.n, dtype=torch.float64)
    w = losses.LossWeights(0.7, 1.3, tuple(0.5 + i for i in range(system.n)))
    out = []
    for cls in (_OldObjective, Objective):
        net = _net(system, structure, with_K)
        obj = cls(system, net, x, y, lam=2.0, P=P, weights=w, loss=kind, margin=0.1,
                  chunk_points=16, workers=1)
        out.append(_grads(obj))
    (v_old, g_old), (v_new, g_new) = out
    assert v_new == v_old
    assert v_new.mpdi > 0  # the case is not trivially zero
    assert all(torch.equal(a, b) for a, b in zip(g_old, g_new))


@pytest.mark.parametrize("which,structure,with_K", [("vdp", "direct", True),
                                                    ("vdp", "structural", True),
                                                    ("three", "structural", False),
                                                    ("three", "direct", False)])
def test_cegis_head_is_the_old_head_bit_for_bit(system3, which, structure, with_K):
    system = load_system("vdp") if which == "vdp" else system3
    x, y = collocation_points(system, 45, 4)
    P = torch.as_tensor(system.P, dtype=torch.float64)
    out = []
    for cls in (_OldCertObjective, CertObjective):
        net = _net(system, structure, with_K, seed=2)
        obj = cls(system, net, x, y, lam=1.0, P=P, margin=0.3, lip_weight=0.05,
                  lip_power=3.0, mpdi_weight=2.0, workers=1)
        values, grads = _grads(obj)
        out.append((values, obj.last_lip, obj.last_lip_max, grads))
    (v_old, l_old, lm_old, g_old), (v_new, l_new, lm_new, g_new) = out
    assert (v_new, l_new, lm_new) == (v_old, l_old, lm_old)
    assert v_new.mpdi > 0 and l_new > 0
    assert all(torch.equal(a, b) for a, b in zip(g_old, g_new))


def test_seeded_training_ends_on_the_old_heads_weights(monkeypatch):
    """A seeded tiny run (Adam then L-BFGS, structural with K, and direct) gives the same
    weights with the ported head as with the frozen old one."""
    system = load_system("vdp")
    for structure in ("direct", "structural"):
        cfg = make_config(system, "tiny", adam_iters=15, lbfgs_iters=10, points=120,
                          structure=structure)
        start = train_module._new_network(system, cfg)
        with torch.no_grad():
            start.K.copy_(torch.tensor([[0.4], [-0.3]]))
        nets = []
        for cls in (_OldObjective, Objective):
            monkeypatch.setattr(train_module, "Objective", cls)
            nets.append(train_module.train(system, cfg, network=start).network)
        old, new = (dict(n.state_dict()) for n in nets)
        assert old.keys() == new.keys()
        for key in old:
            torch.testing.assert_close(new[key], old[key], rtol=1e-6, atol=1e-7)


def test_seeded_cegis_steps_end_on_the_old_heads_weights():
    system = load_system("vdp")
    x, y = collocation_points(system, 200, 5)
    P = torch.as_tensor(system.P, dtype=torch.float64)
    weights = []
    for cls in (_OldCertObjective, CertObjective):
        net = _net(system, "structural", True, seed=3)
        obj = cls(system, net, x, y, lam=1.0, P=P, margin=0.2, lip_weight=0.05,
                  lip_power=8.0, mpdi_weight=10.0, workers=1)
        opt = Adam(obj.params, lr=1e-2)
        for _ in range(20):
            obj.evaluate(grad=True)
            opt.step()
        obj.close()
        weights.append([prm.detach().clone() for prm in obj.params])
    for a, b in zip(*weights):
        torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-7)
