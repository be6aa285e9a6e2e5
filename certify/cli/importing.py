"""`certify import` and the model-from-elsewhere path of `certify run`.

Both read the spec (`--system`), the model, and the design values lam and P (flags, else the
spec's); `import` writes a normal checkpoint (`certify.model.checkpoint.save`, with where the model
came from in its training record), `run` builds the same `Checkpoint` in memory.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from certify.errors import CertifyError
from certify.model.checkpoint import Checkpoint, save, versions
from certify.model.importers import ImportedModel, read_model
from certify.model.importers.torch_model import is_torchscript
from certify.model.metric import MetricError, PolyMetric
from certify.model.problem import Problem
from certify.spec.system import System, load_system, parse_metric, validate_lam, validate_metric

MODEL_FLAGS = ("lam", "metric", "activation", "structure")


def imported_problem(args: argparse.Namespace, model_path: str
                     ) -> tuple[Problem, ImportedModel]:
    """The spec, the model read against it, lam and P (flags, else the spec's) and the spec's
    metric that follows the state, if it has one."""
    system: System = load_system(args.system)
    model = read_model(model_path, system.n, system.p, activation=args.activation,
                       structure=args.structure, box=np.vstack([system.X, system.Y]))
    lam = system.lam if args.lam is None else validate_lam(args.lam, "--lam")
    P = system.P if args.metric is None else validate_metric(
        parse_metric(args.metric, system.n), system.n, "--metric")
    metric = None
    if system.state_metric is not None:
        try:
            metric = PolyMetric.from_dict(system.state_metric, system.n)
        except MetricError as exc:
            raise CertifyError(f"{args.system}: [design.state_metric]: {exc}") from None
    return Problem(system=system, network=model.network(), lam=lam, P=P, metric=metric), model


def describe(model: ImportedModel) -> str:
    return (f"{model.source_format}, {model.activation}, hidden {model.hidden}, "
            f"{model.structure}")


def run_import(args: argparse.Namespace) -> int:
    """`certify import MODEL --system SPEC -o OUT.ckpt`: write a normal checkpoint."""
    problem, model = imported_problem(args, args.model)
    sha = save(args.output, system=problem.system, network=problem.network, lam=problem.lam,
               P=problem.P, training=model.provenance(), metric=problem.metric)
    print(f"imported {args.model} ({describe(model)}) for {problem.system.name}, lam="
          f"{problem.lam:g} -> {args.output} (sha256 {sha[:12]})")
    for note in model.notes:
        print(f"  note: {note}")
    return 0


def checkpoint_for_run(args: argparse.Namespace) -> Any:
    """What `certify run` verifies: the checkpoint, or with --system the imported model
    (with its design values: --lam, --metric, else the spec's)."""
    from certify.model import checkpoint as ckpt_mod

    path = args.checkpoint
    if args.system is None:  # --lam, --metric: overrides, applied by `verify`
        if Path(path).suffix.lower() == ".onnx" or (Path(path).is_file()
                                                     and is_torchscript(Path(path))):
            raise CertifyError(f"{path} is a model from elsewhere: give --system SPEC (the "
                               "system it observes), e.g. certify run "
                               f"{path} --system spec.toml")
        return ckpt_mod.load(path)
    problem, model = imported_problem(args, path)
    if not getattr(args, "quiet", False):
        print(f"imported {path} ({describe(model)})", file=sys.stderr)
        for note in model.notes:
            print(f"  note: {note}", file=sys.stderr)
    return Checkpoint(problem=problem, path=str(path), sha256=model.sha256,
                      training=model.provenance(), versions=versions(), created="")
