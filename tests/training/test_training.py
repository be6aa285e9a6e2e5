"""Training: losses on hand-computed matrices, the hand-written gradient against autograd,
the optimisers against torch.optim, determinism, n-state specs, and the `train` CLI hook."""

from __future__ import annotations

import argparse
import io

import numpy as np
import pytest
import torch

from certify.errors import CertifyError, SettingsError
from certify.model import checkpoint
from certify.model.kernels import contraction_matrix, gain_terms
from certify.model.network import GainNetwork
from certify.spec.system import load_system, parse_metric
from training import losses
from training.collocation import collocation_points
from training.command import add_train_arguments, parse_hidden, run_train
from training.objective import Objective
from training.optim import LBFGS, Adam
from training.presets import TrainConfig, make_config
from training.train import _new_network, train


def _D(rows) -> torch.Tensor:
    return torch.tensor([rows], dtype=torch.float64)


# ----- losses ----------------------------------------------------------------------------

def test_minor_loss_on_hand_computed_matrices():
    rho = (1.0, 0.1)
    assert losses.minor_loss(_D([[-1.0, 0.0], [0.0, -2.0]]), rho).item() == 0.0
    # Delta1 = 1 > 0 (penalty 1), Delta2 = -1 < 0 (penalty 1 * 0.1)
    assert losses.minor_loss(_D([[1.0, 0.0], [0.0, -1.0]]), rho).item() == pytest.approx(1.1)
    # Delta1 = -1 fine, Delta2 = (-1)(1) - 4 = -5: penalty 0.1 * 5
    assert losses.minor_loss(_D([[-1.0, 2.0], [2.0, 1.0]]), rho).item() == pytest.approx(0.5)
    # mean over the batch
    both = torch.cat([_D([[1.0, 0.0], [0.0, -1.0]]), _D([[-1.0, 0.0], [0.0, -2.0]])])
    assert losses.minor_loss(both, rho).item() == pytest.approx(0.55)


def test_minor_loss_blind_spot_diag_0_1_but_eigen_loss_sees_it():
    """D = diag(0, 1) is not negative semidefinite, yet every sign-fixed minor penalty is 0."""
    D = _D([[0.0, 0.0], [0.0, 1.0]])
    assert losses.minor_loss(D, (1.0, 1.0)).item() == 0.0
    assert losses.eigen_loss(D).item() == pytest.approx(1.0)
    assert losses.eigen_loss(D, margin=0.5).item() == pytest.approx(1.5)
    assert losses.eigen_loss(D, squared=True, margin=0.5).item() == pytest.approx(2.25)
    assert losses.eigen_loss(_D([[-1.0, 0.0], [0.0, -2.0]]), margin=0.5).item() == 0.0


def test_leading_minors_match_det_for_any_n():
    g = torch.Generator().manual_seed(0)
    for n in range(1, 6):
        D = torch.randn(7, n, n, generator=g, dtype=torch.float64)
        ref = torch.stack([torch.linalg.det(D[:, :k, :k]) for k in range(1, n + 1)], -1)
        torch.testing.assert_close(losses.leading_minors(D), ref)
        signs = torch.tensor([(-1.0) ** (k + 1) for k in range(1, n + 1)], dtype=D.dtype)
        torch.testing.assert_close(losses.minor_penalties(D), torch.relu(ref * signs))


@pytest.mark.parametrize("n", [1, 2, 3])
def test_closed_form_minor_gradient_matches_autograd(n):
    D = torch.randn(40, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    rho = (0.7, 0.3, 1.1)[:n]
    value, grad = losses.minor_loss_sum_and_grad(D, rho)
    Dl = D.clone().requires_grad_(True)
    ref = losses.minor_loss(Dl, rho, reduce="sum")
    (ref_grad,) = torch.autograd.grad(ref, [Dl])
    assert value.item() == pytest.approx(ref.item(), rel=1e-12)
    torch.testing.assert_close(grad, ref_grad)


def test_eigen_loss_gradient_is_finite_at_repeated_eigenvalues():
    D = _D([[-1.0, 0.0], [0.0, -1.0]]).requires_grad_(True)
    (g,) = torch.autograd.grad(losses.eigen_loss(D, margin=2.0), [D])
    assert torch.all(torch.isfinite(g))


def test_bc_loss_zero_for_structural_network(system3):
    torch.manual_seed(0)
    net = GainNetwork(3, 2, (6, 5), structure="structural").double()
    x, _ = collocation_points(system3, 50, 1)
    k = gain_terms(system3, net, x, system3.h(x), with_dy=False).k
    assert losses.bc_loss(k).item() == 0.0
    xs, ys = collocation_points(system3, 50, 2)
    obj = Objective(system3, net, xs, ys, lam=0.5, P=torch.as_tensor(system3.P),
                    weights=losses.LossWeights(1.0, 1.0, (1.0, 1.0, 1.0)), workers=1)
    assert obj.evaluate(grad=False).bc == 0.0


def test_collocation_points_are_seeded_and_inside_the_box(system3):
    x1, y1 = collocation_points(system3, 500, 7)
    x2, y2 = collocation_points(system3, 500, 7)
    x3, _ = collocation_points(system3, 500, 8)
    assert torch.equal(x1, x2) and torch.equal(y1, y2) and not torch.equal(x1, x3)
    X, Y = torch.as_tensor(system3.X), torch.as_tensor(system3.Y)
    assert torch.all((x1 >= X[:, 0]) & (x1 <= X[:, 1]))
    assert torch.all((y1 >= Y[:, 0]) & (y1 <= Y[:, 1]))


# ----- the fast objective against a plain autograd reference -----------------------------

def _reference_loss(system, net, x, y, P, lam, w, kind, margin):
    terms = gain_terms(system, net, x, y, with_dy=False)
    D = contraction_matrix(system.jac_f(x), terms.dk_dx, P, lam)
    if kind == "minors":
        mpdi = losses.minor_loss(D, w.rho)
    else:
        mpdi = losses.eigen_loss(D, margin, squared=kind == "eigen_squared")
    bc = losses.bc_loss(gain_terms(system, net, x, system.h(x), with_dy=False).k)
    return losses.total_loss(mpdi, bc, w), mpdi, bc


@pytest.mark.parametrize("which,structure,with_K,kind", [
    ("vdp", "direct", False, "minors"),
    ("vdp", "direct", True, "eigen"),
    ("vdp", "structural", True, "minors"),
    ("three", "direct", True, "minors"),
    ("three", "structural", False, "eigen_squared"),
])
def test_objective_value_and_gradient_match_autograd(system3, which, structure, with_K, kind):
    system = load_system("vdp") if which == "vdp" else system3
    torch.manual_seed(1)
    net = GainNetwork(system.n, system.p, (7, 6, 5), structure=structure).double()
    if with_K:
        net.K.copy_(torch.randn(system.n, system.p, dtype=torch.float64))
    x, y = collocation_points(system, 37, 3)
    P = torch.as_tensor(system.P) if which == "three" else torch.tensor(
        [[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    w = losses.LossWeights(0.7, 1.3, tuple(0.5 + i for i in range(system.n)))
    obj = Objective(system, net, x, y, lam=2.0, P=P, weights=w, loss=kind, margin=0.1,
                    chunk_points=10, workers=2)
    values = obj.evaluate(grad=True)
    obj.close()
    total, mpdi, bc = _reference_loss(system, net, x, y, P, 2.0, w, kind, 0.1)
    ref_grads = torch.autograd.grad(total, obj.params)
    assert values.total == pytest.approx(total.item(), rel=1e-12, abs=1e-14)
    assert values.mpdi == pytest.approx(mpdi.item(), rel=1e-12, abs=1e-14)
    assert values.bc == pytest.approx(bc.item(), rel=1e-12, abs=1e-14)
    for got, ref in zip(obj.params, ref_grads):
        torch.testing.assert_close(got.grad, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("hidden,activation,structure,kind", [
    ((30, 30, 30), "tanh", "direct", "minors"),  # the paper preset's shape: padded to 32
    ((16, 8), "tanh", "structural", "eigen"),  # multiples of 8: no padding
    ((7, 5), "softplus", "direct", "minors"),  # padded units of a nonzero f(0)
])
def test_float32_objective_matches_the_float64_autograd_reference(hidden, activation,
                                                                  structure, kind):
    """The float32 training path (padded widths, tanh as 2 sigmoid(2x) - 1, the hand-written
    reverse pass) against plain autograd through `gain_terms` in float64 on the same weights:
    equal to float32 rounding."""
    system = load_system("vdp")
    torch.manual_seed(7)
    net64 = GainNetwork(2, 1, hidden, structure=structure, activation=activation).double()
    net64.K.copy_(torch.tensor([[0.5], [-0.25]], dtype=torch.float64))
    net32 = GainNetwork.from_architecture(net64.architecture())
    net32.load_state_dict(net64.state_dict())
    net32 = net32.float().requires_grad_(True)
    x, y = collocation_points(system, 300, 5)
    P = torch.tensor([[2.0, 0.3], [0.3, 1.0]], dtype=torch.float64)
    w = losses.LossWeights(0.7, 1.3, (1.0, 0.1))
    obj = Objective(system, net32, x, y, lam=1.0, P=P, weights=w, loss=kind, margin=0.1,
                    chunk_points=128, workers=2)
    values = obj.evaluate(grad=True)
    obj.close()
    total, mpdi, bc = _reference_loss(system, net64, x, y, P, 1.0, w, kind, 0.1)
    ref_grads = torch.autograd.grad(total, list(net64.parameters()))
    assert values.total == pytest.approx(total.item(), rel=1e-5)
    assert values.mpdi == pytest.approx(mpdi.item(), rel=1e-5)
    assert values.bc == pytest.approx(bc.item(), rel=1e-5, abs=1e-9)
    for got, ref in zip(obj.params, ref_grads):
        scale = float(ref.abs().max())
        torch.testing.assert_close(got.grad.double(), ref, rtol=1e-4, atol=1e-5 * scale)


def test_objective_gradient_does_not_depend_on_worker_count():
    system = load_system("vdp")
    cfg = make_config(system, "tiny")
    x, y = collocation_points(system, 300, 0)
    w = losses.LossWeights(cfg.mu1, cfg.mu2, cfg.rho)
    grads = []
    for workers in (1, 2):
        net = _new_network(system, cfg)
        obj = Objective(system, net, x, y, lam=2.5, P=torch.eye(2), weights=w,
                        chunk_points=64, workers=workers)
        obj.evaluate(grad=True)
        obj.close()
        grads.append([p.grad.clone() for p in obj.params])
    assert all(torch.equal(a, b) for a, b in zip(*grads))


def test_optimisers_reproduce_torch_optim_exactly():
    """Our Adam and L-BFGS (strong Wolfe) take the same steps as torch.optim's."""
    system = load_system("vdp")
    cfg = make_config(system, "tiny")
    x, y = collocation_points(system, 150, 0)
    w = losses.LossWeights(cfg.mu1, cfg.mu2, cfg.rho)

    def fresh():
        net = _new_network(system, cfg).requires_grad_(True)
        return Objective(system, net, x, y, lam=2.5, P=torch.eye(2), weights=w, workers=1)

    ours = fresh()
    adam = Adam(ours.params, lr=1e-2)
    for _ in range(15):
        ours.evaluate()
        adam.step()
    lbfgs = LBFGS(ours.params, lr=1.0, max_iter=25)
    lbfgs.run(lambda: ours.evaluate().total)

    ref = fresh()
    adam_ref = torch.optim.Adam(ref.params, lr=1e-2)
    for _ in range(15):
        ref.evaluate()
        adam_ref.step()
    lbfgs_ref = torch.optim.LBFGS(ref.params, lr=1.0, max_iter=25,
                                  line_search_fn="strong_wolfe")
    lbfgs_ref.step(lambda: torch.tensor(ref.evaluate().total, dtype=torch.float64))
    for a, b in zip(ours.params, ref.params):
        assert torch.equal(a, b)
    state = lbfgs_ref.state[ref.params[0]]
    assert (lbfgs.n_iter, lbfgs.func_evals) == (state["n_iter"], state["func_evals"])


# ----- training runs ---------------------------------------------------------------------

def test_short_training_lowers_the_loss_and_records_history():
    system = load_system("vdp")
    result = train(system, make_config(system, "tiny"))
    hist = result.history
    assert len(hist["adam"]["total"]) == 30
    assert len(hist["lbfgs"]["total"]) == result.counts["lbfgs_evaluations"] >= 30
    assert hist["lbfgs"]["iteration"][-1] == result.counts["lbfgs_iterations"]
    first = hist["adam"]["total"][0]
    assert result.final["total"] < 0.5 * first
    assert result.network.layers[0].weight.dtype == torch.float64
    assert set(result.timings) >= {"setup", "adam", "lbfgs", "total"}


@pytest.mark.slow
def test_same_seed_same_weights_and_other_seed_differs():
    system = load_system("vdp")
    runs = [train(system, make_config(system, "tiny", seed=s)).network for s in (3, 3, 4)]
    sd = [r.state_dict() for r in runs]
    assert all(torch.equal(sd[0][k], sd[1][k]) for k in sd[0])
    assert not all(torch.equal(sd[0][k], sd[2][k]) for k in sd[0])


@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_three_state_two_output_spec_trains(system3, structure):
    config = make_config(system3, "tiny", structure=structure, adam_lr=1e-2)
    result = train(system3, config)
    assert result.network.n == 3 and result.network.p == 2
    assert result.final["total"] < result.history["adam"]["total"][0]
    if structure == "structural":
        assert result.final["bc"] == 0.0


def test_eigen_loss_training_runs():
    system = load_system("vdp")
    result = train(system, make_config(system, "tiny", loss="eigen", margin=0.1))
    assert np.isfinite(result.final["total"])


# ----- presets and validation --------------------------------------------------------------

def test_paper_preset_reads_the_spec_weights():
    vdp = make_config(load_system("vdp"))
    assert (vdp.mu1, vdp.mu2, vdp.rho) == (1e-3, 1.0, (1.0, 0.1))
    assert (vdp.points, vdp.hidden, vdp.adam_iters, vdp.lbfgs_iters) == (4000, (30,) * 5,
                                                                         500, 500)
    assert (vdp.adam_lr, vdp.lbfgs_lr, vdp.loss, vdp.dtype) == (1e-3, 1.0, "minors", "float32")
    assert vdp.lam == 2.5 and vdp.P == ((1.0, 0.0), (0.0, 1.0))
    duf = make_config(load_system("duffing"))
    assert (duf.mu1, duf.mu2, duf.rho) == (1.0, 1.0, (1.0, 1.0))


@pytest.mark.parametrize("overrides,field", [
    ({"points": 0}, "points"), ({"seed": -1}, "seed"), ({"hidden": (30, 0)}, "hidden"),
    ({"lam": float("nan")}, "lam"), ({"adam_lr": 0.0}, "adam_lr"), ({"loss": "l2"}, "loss"),
    ({"rho": (1.0,)}, "rho"), ({"P": ((1.0, 2.0), (2.0, 1.0))}, "P"),
    ({"structure": "dense"}, "structure"), ({"dtype": "float16"}, "dtype"),
])
def test_bad_settings_are_refused_naming_the_field(overrides, field):
    with pytest.raises(SettingsError, match=rf"training: {field}\b"):
        make_config(load_system("vdp"), "paper", **overrides)


def test_unknown_preset_and_setting_are_refused():
    with pytest.raises(SettingsError, match="unknown preset 'fast'.*paper, tiny"):
        make_config(load_system("vdp"), "fast")
    with pytest.raises(SettingsError, match="unknown setting"):
        make_config(load_system("vdp"), "paper", epochs=3)
    with pytest.raises(SettingsError):
        TrainConfig(points=True)


# ----- the command-line hook ---------------------------------------------------------------

def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.mark.parametrize("text,message", [
    ("[[1,2],[2,1]]", "positive definite"),
    ("[[1,0.5],[0,1]]", "symmetric"),
    ("[[1,0],[0,1],[1,1]]", "square matrix"),
    ("[[1,0,0],[0,1,0],[0,0,1]]", "must be 2x2"),
    ("__import__('os').system('touch /tmp/pwned')", "must be a matrix"),
    ("[[1,'a'],['a',1]]", "square matrix of numbers"),
    ("[[1,0],[0,Infinity]]", "non-finite"),
])
def test_bad_metric_refused_with_a_clear_message(tmp_path, text, message):
    with pytest.raises(CertifyError, match=message):
        run_train(_parse("vdp", "-o", str(tmp_path / "x.ckpt"), "--metric", text, "--quiet"))
    assert not (tmp_path / "x.ckpt").exists()


@pytest.mark.parametrize("text", ["30,x", "0", "", "30,,30", "-5", "3.5"])
def test_bad_hidden_refused_with_a_clear_message(tmp_path, text):
    with pytest.raises(SettingsError, match="--hidden must be comma-separated positive"):
        run_train(_parse("vdp", "-o", str(tmp_path / "x.ckpt"), "--hidden", text, "--quiet"))


def test_parsers_accept_good_values():
    assert parse_hidden("30, 30,30") == (30, 30, 30)
    assert parse_metric("[[2, 0.5], [0.5, 1]]", 2) == ((2.0, 0.5), (0.5, 1.0))
    assert parse_metric("((2, 0), (0, 1))") == ((2.0, 0.0), (0.0, 1.0))


def test_bad_numbers_and_unknown_system_are_refused(tmp_path):
    out = str(tmp_path / "x.ckpt")
    with pytest.raises(SettingsError, match=r"points \(--points\)"):
        run_train(_parse("vdp", "-o", out, "--points", "0", "--quiet"))
    with pytest.raises(SettingsError, match=r"lam \(--lam\)"):
        run_train(_parse("vdp", "-o", out, "--lam", "-1", "--quiet"))
    with pytest.raises(CertifyError, match="unknown system 'nosuch'"):
        run_train(_parse("nosuch", "-o", out, "--quiet"))
    with pytest.raises(CertifyError, match="is a directory"):
        run_train(_parse("vdp", "-o", str(tmp_path), "--preset", "tiny", "--quiet"))


def test_run_train_writes_a_checkpoint_that_loads_with_its_history(tmp_path):
    out = tmp_path / "vdp.ckpt"
    stream = io.StringIO()
    code = run_train(_parse("vdp", "-o", str(out), "--preset", "tiny", "--seed", "5",
                            "--metric", "[[2,0.5],[0.5,1]]", "--lam", "1.5",
                            "--hidden", "6,6", "--adam-iters", "20", "--lbfgs-iters", "10"),
                     stdout=stream)
    assert code == 0
    text = stream.getvalue()
    assert "train adam" in text and "train lbfgs" in text and f"wrote {out}" in text
    ck = checkpoint.load(out)
    assert ck.problem.lam == 1.5
    np.testing.assert_allclose(ck.problem.P, [[2.0, 0.5], [0.5, 1.0]])
    assert ck.problem.network.hidden == [6, 6]
    assert ck.problem.network.layers[0].weight.dtype == torch.float64
    rec = ck.training
    assert rec["seed"] == 5 and rec["config"]["preset"] == "tiny"
    assert rec["config"]["hidden"] == [6, 6]
    assert len(rec["history"]["adam"]["total"]) == 20
    assert len(rec["history"]["lbfgs"]["total"]) == rec["counts"]["lbfgs_evaluations"]
    assert {"adam", "lbfgs", "total"} <= set(rec["timings"])
    assert "torch" in rec["versions"] and np.isfinite(rec["final"]["total"])


def test_quiet_prints_nothing(tmp_path):
    stream = io.StringIO()
    run_train(_parse("duffing", "-o", str(tmp_path / "d.ckpt"), "--preset", "tiny",
                     "--quiet"), stdout=stream)
    assert stream.getvalue() == ""
    assert checkpoint.load(tmp_path / "d.ckpt").problem.system.name == "duffing"
