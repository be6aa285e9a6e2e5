"""A verification problem as plain data, rebuilt once per worker process.

`problem_payload(problem)` holds only plain data (the spec's TOML text, the network's
architecture and float64 weights as numpy arrays, lam, P), so it pickles small and safely
for Dask workers; `problem_from_payload` rebuilds the `Problem` on the worker and caches it
by the payload's digest (`certify.search.distributed.executor.worker_cache`), so a worker parses
the spec and
builds the network once per proof, not once per chunk.

`mpdi_grid_chunk` is the MPDI grid sweep's chunk task (module level: picklable): the same
`certify.search.falsify.sweep_range` the in-process sweep runs, on a range of grid indices. The
prover's box task (`certify.prove.mpdi.mpdi_box_chunk`) rebuilds its problem here too.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from certify.model.problem import NoiseInput, Problem
from certify.search.distributed.executor import payload_key, worker_cache

#: the keys of `problem_payload` (a task's payload may carry more)
PROBLEM_KEYS = ("spec", "name", "architecture", "state", "lam", "P", "shift", "noise")


def problem_payload(problem: Problem) -> dict[str, Any]:
    """Plain data from which `problem_from_payload` rebuilds `problem` exactly."""
    net = problem.network
    state = {k: v.detach().to(torch.float64).cpu().numpy().copy()
             for k, v in net.state_dict().items()}
    return {"spec": problem.system.source, "name": problem.system.name,
            "architecture": net.architecture(), "state": state, "lam": float(problem.lam),
            "P": np.asarray(problem.P, dtype=np.float64).copy(),
            "shift": None if problem.shift is None
            else np.asarray(problem.shift, dtype=np.float64).copy(),
            "noise": None if problem.noise is None else dataclasses.asdict(problem.noise)}


def _build(payload: dict[str, Any]) -> Problem:
    from certify.model.network import GainNetwork
    from certify.spec.system import System

    system = System.from_text(payload["spec"], origin=f"system {payload['name']}")
    net = GainNetwork.from_architecture(payload["architecture"]).double()
    net.load_state_dict({k: torch.as_tensor(v) for k, v in payload["state"].items()})
    noise = payload.get("noise")
    return Problem(system=system, network=net, lam=payload["lam"], P=payload["P"],
                   shift=payload.get("shift"), noise=None if noise is None else NoiseInput(**noise))


def problem_from_payload(payload: dict[str, Any]) -> Problem:
    """The `Problem` of `payload`, built once per process (cached by digest)."""
    key = payload.get("key") or payload_key(payload)
    return worker_cache("problem:" + key, lambda: _build(payload))


def mpdi_payload(problem: Problem, lam: float, float32_screen: bool,
                 device: str = "cpu") -> dict[str, Any]:
    """What an MPDI grid-sweep task needs besides the grid (plain data, with its digest);
    `device`: where the worker evaluates (its results come back on the CPU)."""
    payload = problem_payload(problem)
    payload.update(grid_lam=float(lam), float32_screen=bool(float32_screen),
                   device=str(device))
    payload["key"] = payload_key(payload)
    return payload


def _grid_kernels(payload: dict[str, Any]) -> tuple[Any, Any]:
    from certify.search.grid import GridKernel

    def build() -> tuple[Any, Any]:
        from certify.arith.device import resolve_device

        problem = problem_from_payload({k: payload[k] for k in PROBLEM_KEYS})
        problem = problem.on(resolve_device(payload.get("device", "cpu")))
        exact = GridKernel(problem, payload["grid_lam"])
        screen = (GridKernel(problem, payload["grid_lam"], dtype=torch.float32)
                  if payload["float32_screen"] else None)
        return exact, screen

    return worker_cache("grid:" + payload["key"], build)


def mpdi_grid_chunk(payload: dict[str, Any], start: int, stop: int, tol: float,
                    use_screen: bool) -> list[tuple]:
    """Sweep grid indices [start, stop) in sub-chunks of `payload['grid']['chunk']`; one
    `sweep_range` result per sub-chunk, in order."""
    from certify.search.falsify import sweep_range
    from certify.search.threads import torch_threads

    exact, screen = _grid_kernels(payload)
    grid = payload["grid"]  # added by certify.search.falsify for this sweep
    device = exact.P.device
    lo = torch.as_tensor(grid["lo"], dtype=torch.float64, device=device)
    hi = torch.as_tensor(grid["hi"], dtype=torch.float64, device=device)
    step = grid["chunk"]
    with torch_threads(1), torch.no_grad():
        parts = [sweep_range(exact, screen if use_screen else None, lo, hi, grid["shape"],
                             s, min(stop, s + step), grid["threshold"], tol, grid["keep"])
                 for s in range(start, stop, step)]
    return [(pts.cpu(), vals.cpu(), above, bad) for pts, vals, above, bad in parts]
