"""A learned gain for vdp against the metric certificate of examples/vdp_metric.ckpt.

Starts from that checkpoint (the linear gain K in the structural network k = (G(x, y) + K)
(y - h(x)) with G = 0, its constant metric P, rate lam and its metric M(x), kept fixed) and
trains G with Adam against:

* on the tube of the checkpoint's last metric stage (widened by `--widen`): the mu the metric
  inequality needs at the stage's rate alpha (the top `--top` fraction of the sampled points,
  the bound is sqrt(mu / alpha) vbar / sqrt(m_min)), with the state block of its matrix kept
  negative definite;
* over X x Y: the MPDI's lam_max(D) with P and the checkpoint's rate, kept below `-margin`
  (the first stage: the constant-metric certificates over X x Y);
* over X x Y: `--pull` |G|^2, keeping the gain near the linear one off the tube.

Then `certify.verify` proves the candidate (training.proved.certified_bound) and, with
`--out`, the checkpoint is written (network, lam, P, M(x)); `certify run` proves it again.
Prints JSON lines: the training's sampled figures every 50 steps, then the proved bounds of the
linear and the learned gain.

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/vdp_metric_learned.py \
        --out examples/vdp_metric_learned.ckpt
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch

from certify.design.bound import pointwise_terms
from certify.enclose.metric import point_matrix
from certify.model import checkpoint
from certify.prove import metric as pm
from certify.settings import VerifySettings
from certify.verify import verify
from training.collocation import collocation_points
from training.proved import REPORT_VBAR, certified_bound, copy_network


def needed_mu(system, net, metric, alpha: float, z: torch.Tensor) -> tuple[torch.Tensor,
                                                                            torch.Tensor]:
    """(mu the metric inequality needs at rate alpha at the points z [N, n + p], lam_max of
    its state block X) -- mu is meaningful where lam_max(X) < 0."""
    n = system.n
    N = point_matrix(system, net, metric, alpha, 1.0, z)
    X, MB = N[:, :n, :n], 2.0 * N[:, :n, n:]
    top = torch.linalg.eigvalsh(X)[:, -1]
    eye = torch.eye(n, dtype=z.dtype).expand_as(X)
    S = -X + torch.relu(1e-3 - (-top))[:, None, None] * eye  # keep -X positive definite
    L = torch.linalg.cholesky(S)
    Zm = torch.linalg.solve_triangular(L, MB, upper=False)
    mu = torch.linalg.eigvalsh(Zm.transpose(1, 2) @ Zm)[:, -1] / 2.0
    return mu, top


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="examples/vdp_metric.ckpt")
    ap.add_argument("--out", default=None)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--points", type=int, default=4000)
    ap.add_argument("--top", type=float, default=0.02)
    ap.add_argument("--widen", type=float, default=1.1)
    ap.add_argument("--margin", type=float, default=0.25)
    ap.add_argument("--pull", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    torch.manual_seed(a.seed)
    ck = checkpoint.load(a.base)
    pr = ck.problem
    system, metric, P, lam = pr.system, pr.metric, pr.P, pr.lam
    # the checkpoint's own certificate: its last metric stage's tube and rate
    cert = verify(ck, VerifySettings(noise=REPORT_VBAR, skip=("simulation",)), figures=False)
    mb = cert.checks["metric_bound"]
    tau, alpha = float(mb.stages[-1]["tau"]), float(mb.stages[-1]["alpha"])
    base = {"verdict": cert.verdict, "ultimate": cert.checks["bounds"].ultimate,
            "metric_ultimate": mb.ultimate, "metric_tau": tau}
    net = copy_network(pr.network).train()
    params = [q for layer in net.layers for q in (layer.weight, layer.bias)]
    for q in params:
        q.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=a.lr)
    z = pm.sample_domain(system, pm.domain_for(system, a.widen * tau), a.points, a.seed + 1)
    xh, y = collocation_points(system, a.points, a.seed + 2)
    n, p = system.n, system.p
    k = max(1, int(a.top * len(z)))
    hist = []
    for step in range(a.steps + 1):
        mu, top = needed_mu(system, net, metric, alpha, z)
        D, _ = pointwise_terms(system, net, P, 4.0 * lam, xh, y)
        lD = torch.linalg.eigvalsh(D)[:, -1]
        G = net(torch.cat([xh, y], 1)).reshape(-1, n, p)
        loss = (torch.topk(mu, k).values.mean() / 100.0
                + 10.0 * torch.relu(top + 0.05).mean()
                + 10.0 * torch.relu(lD + a.margin).mean()
                + a.pull * (G ** 2).mean())
        if step % 50 == 0:
            mu, lD, G, top = mu.detach(), lD.detach(), G.detach(), top.detach()
            hist.append({"step": step, "max_mu": float(mu.max()), "top_mu": float(
                torch.topk(mu, k).values.mean()), "max_lD": float(lD.max()),
                "max_X": float(top.max()), "G_rms": float((G ** 2).mean().sqrt())})
            print(json.dumps(hist[-1]), flush=True)
        if step == a.steps:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = copy_network(net).eval().requires_grad_(False)
    learned = certified_bound(system, final, lam, P, metric=metric, vbar=REPORT_VBAR)
    row = {"bench": "vdp_metric_learned", "alpha": alpha, "tau": tau,
           "linear": base, "learned": learned, "args": vars(a),
           "seconds": time.perf_counter() - t0}
    print(json.dumps(row, default=str), flush=True)
    if a.out and learned.get("metric_ultimate") is not None:
        training = {"preset": "bound", "returned": "learned with M(x)", "lam": lam,
                    "report_vbar": REPORT_VBAR, "script": "bench/vdp_metric_learned.py",
                    "args": vars(a), "base": a.base, "certified": learned}
        checkpoint.save(a.out, system=system, network=final, lam=lam, P=P, metric=metric,
                        training=training)
    return 0 if learned.get("ultimate") is not None and math.isfinite(learned["ultimate"]) \
        else 1


if __name__ == "__main__":
    raise SystemExit(main())
