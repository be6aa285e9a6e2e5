"""`certify train`: the command-line hook (arguments, progress display, checkpoint writing).

`certify.cli` calls `add_train_arguments(parser)` and `run_train(args)`; bad
values raise `CertifyError` subclasses, which the CLI turns into one line and exit code 2.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from certify.errors import CertifyError, SettingsError
from training.preflight import EXIT_INFEASIBLE, Infeasible
from training.presets import PRESETS, make_config, preset_summary


def parse_hidden(text: str) -> tuple[int, ...]:
    """'30,30,30' -> (30, 30, 30); anything else is refused naming --hidden."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        widths = tuple(int(p) for p in parts)
    except ValueError:
        widths = ()
    if not widths or any(w < 1 for w in widths):
        raise SettingsError(f"--hidden must be comma-separated positive layer widths like "
                            f"30,30,30; got {text!r}")
    return widths


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of `certify train`."""
    from certify.spec import builtin

    names = ", ".join(builtin.names())
    parser.add_argument("system", nargs="?",
                        help=f"built-in system name ({names}) or a spec .toml path")
    parser.add_argument("--system", dest="system_option", metavar="SYSTEM",
                        help="the same, as an option (as `certify run` takes it)")
    parser.add_argument("-o", "--output", required=True, help="checkpoint file to write (.ckpt)")
    recipes = "; ".join(f"{name}: {preset_summary(name)}" for name in PRESETS)
    parser.add_argument("--preset", default="paper", choices=list(PRESETS), metavar="PRESET",
                        help=f"training recipe (default: paper). {recipes}")
    parser.add_argument("--lam", type=float, default=None,
                        help="contraction rate lam (default: the system's)")
    parser.add_argument("--metric", default=None,
                        help="constant metric P as [[a,b],[b,c]] (default: the system's)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    parser.add_argument("--points", type=int, default=None,
                        help="collocation points (paper: 4000)")
    parser.add_argument("--hidden", default=None,
                        help="hidden widths, comma-separated (paper: 30,30,30,30,30)")
    parser.add_argument("--adam-iters", type=int, default=None, dest="adam_iters",
                        help="full-batch Adam iterations (paper: 500)")
    parser.add_argument("--lbfgs-iters", type=int, default=None, dest="lbfgs_iters",
                        help="L-BFGS iterations (paper: 500)")
    parser.add_argument("--activation", default=None,
                        help="hidden-layer activation: tanh (default), sigmoid, softplus, silu, "
                             "elu, gelu (C^1 only: relu is refused)")
    parser.add_argument("--curvature-weight", type=float, default=None,
                        dest="curvature_weight",
                        help="weight of the verification-aware term: the variation of dk/dxhat "
                             "over point pairs at a small distance (paper: 0; certified: "
                             "1e-2)")
    parser.add_argument("--curvature-radius", type=float, default=None,
                        dest="curvature_radius",
                        help="that term's pair distance, a fraction of each box side "
                             "(default 0.02)")
    parser.add_argument("--verifier-weight", type=float, default=None,
                        dest="verifier_weight",
                        help="weight of the training term on the prover's box bound over "
                             "sampled sub-boxes (presets that train a network; default 0: off)")
    parser.add_argument("--min-rate", type=float, default=None, dest="min_rate",
                        help="preset bound only: the smallest contraction rate lam the design "
                             "may choose (default: the rate is free; --lam fixes it)")
    parser.add_argument("--no-state-metric", action="store_true", dest="no_state_metric",
                        help="preset bound only: skip the design of a metric M(x) that follows "
                             "the state (the slow part of a free-rate design)")
    parser.add_argument("--force", action="store_true",
                        help="train even when the pre-flight proves that no gain meets the "
                             "MPDI and the boundary condition with this P and lam (presets "
                             "paper, and certified with --metric; the network written cannot "
                             "meet both)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.epilog = EXIT_CODES_TEXT


#: `certify train --help`'s last paragraph
EXIT_CODES_TEXT = (
    "exit codes of train: 0 checkpoint written (presets certified and bound: and proved), "
    "1 checkpoint written but not proved (certified, bound), 2 bad input, 4 internal error, "
    f"{EXIT_INFEASIBLE} nothing trained or written: the pre-flight proves that no gain meets "
    "the MPDI and the boundary condition with this P and lam (--force trains anyway), or the "
    "preset found no design (the message says whether none exists)."
)


class PlainProgress:
    """Progress as plain lines (for logs and CI): one line per `every` iterations."""

    def __init__(self, stream: TextIO, every: int = 100) -> None:
        self.stream, self.every = stream, every
        self.count: dict[str, int] = {}
        self.total: dict[str, float | None] = {}
        self.t0: dict[str, float] = {}

    def start(self, task: str, total: float | None = None) -> None:
        self.count[task], self.total[task], self.t0[task] = 0, total, time.perf_counter()

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None:
        before = self.count.get(task, 0)
        self.count[task] = before + int(advance)
        if self.count[task] // self.every > before // self.every:
            self._line(task, fields)

    def _line(self, task: str, fields: dict[str, object]) -> None:
        terms = "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in fields.items())
        total = self.total.get(task)
        of = f"/{int(total)}" if total else ""
        print(f"train {task:5s} {self.count[task]}{of}  {terms}", file=self.stream, flush=True)

    def finish(self, task: str, message: str = "") -> None:
        took = time.perf_counter() - self.t0.get(task, time.perf_counter())
        print(f"train {task:5s} done in {took:.1f} s  {message}", file=self.stream, flush=True)


class RichProgress:
    """A rich progress bar per phase, with the loss terms beside it (terminals)."""

    def __init__(self) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )
        self._bar = Progress(TextColumn("{task.description:6s}"), BarColumn(),
                             MofNCompleteColumn(), TimeElapsedColumn(),
                             TextColumn("{task.fields[terms]}"))
        self._ids: dict[str, Any] = {}

    def __enter__(self) -> RichProgress:
        self._bar.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._bar.__exit__(*exc)

    def start(self, task: str, total: float | None = None) -> None:
        self._ids[task] = self._bar.add_task(task, total=total, terms="")

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None:
        terms = "  ".join(f"{k} {v:.3e}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in fields.items())
        self._bar.update(self._ids[task], advance=advance, terms=terms)

    def finish(self, task: str, message: str = "") -> None:
        tid = self._ids[task]
        total = self._bar.tasks[[t.id for t in self._bar.tasks].index(tid)].total
        self._bar.update(tid, completed=total, terms=message)


def _config_from_args(args: argparse.Namespace, system: Any) -> Any:
    from certify.spec.system import parse_metric

    hidden = parse_hidden(args.hidden) if getattr(args, "hidden", None) is not None else None
    metric = parse_metric(args.metric, system.n) if getattr(args, "metric", None) else None
    preset = getattr(args, "preset", None) or "paper"
    return make_config(system, preset, lam=getattr(args, "lam", None), P=metric,
                       seed=getattr(args, "seed", None), points=getattr(args, "points", None),
                       hidden=hidden, adam_iters=getattr(args, "adam_iters", None),
                       lbfgs_iters=getattr(args, "lbfgs_iters", None),
                       activation=getattr(args, "activation", None),
                       curvature_weight=getattr(args, "curvature_weight", None),
                       curvature_radius=getattr(args, "curvature_radius", None),
                       verifier_weight=getattr(args, "verifier_weight", None))


def resolve_system(args: argparse.Namespace) -> None:
    """`args.system` from the positional argument or `--system` (one of them, or both
    naming the same system); a clear error otherwise."""
    option = getattr(args, "system_option", None)
    if args.system is not None and option is not None and args.system != option:
        raise SettingsError(f"two systems given: {args.system!r} and --system {option!r}; "
                            "give one")
    args.system = args.system if args.system is not None else option
    if args.system is None:
        raise SettingsError("certify train needs a system: a built-in name or a spec .toml "
                            "(certify train vdp -o vdp.ckpt; see certify systems)")


def run_train(args: argparse.Namespace, stdout: TextIO | None = None) -> int:
    """Train as `args` say and write the checkpoint; returns the exit code (`EXIT_CODES_TEXT`):
    `EXIT_INFEASIBLE`, with the reason on stderr, when the pre-flight or the preset's
    design says nothing can be trained (`training.preflight`).

    Raises `CertifyError` (exit code 2) for a bad system, setting or output path.
    """
    try:
        return _run_train(args, stdout or sys.stdout)
    except Infeasible as exc:
        print(f"certify train: {exc}", file=sys.stderr, flush=True)
        return EXIT_INFEASIBLE


def _run_train(args: argparse.Namespace, out: TextIO) -> int:
    # here, not at the top: they import torch, which `certify train --help` does not need
    from certify.model import checkpoint
    from certify.spec.system import load_system
    from training.train import train

    system = load_system(args.system)
    config = _config_from_args(args, system)
    output = Path(args.output)
    if output.exists() and output.is_dir():
        raise CertifyError(f"--output {output} is a directory; give a file name like "
                           f"{system.name}.ckpt")
    min_rate = getattr(args, "min_rate", None)
    if min_rate is not None and (config.preset != "bound" or not math.isfinite(min_rate)
                                 or min_rate <= 0):
        raise SettingsError(f"training: --min-rate must be a finite number > 0 and applies to "
                            f"preset bound only; got {min_rate!r} with preset {config.preset}")
    if getattr(args, "no_state_metric", False) and config.preset != "bound":
        raise SettingsError(f"training: --no-state-metric applies to preset bound only; got "
                            f"preset {config.preset}")
    from training import preflight

    quiet = bool(getattr(args, "quiet", False))
    if config.preset == "bound" or (config.preset == "certified"
                                    and not getattr(args, "metric", None)):
        preflight.check_designable(system, config.preset)  # they design P themselves
    if config.preset == "bound":  # designed for the error bound (training.bound)
        from training.bound import run_bound

        return run_bound(args, system, config, out)
    if config.preset != "certified" or getattr(args, "metric", None):  # P is given: check it
        preflight.check(system, np.asarray(config.P), config.lam, config.preset,
                        force=bool(getattr(args, "force", False)),
                        log=lambda m: None if quiet else print(m, file=out, flush=True),
                        warn=lambda m: print(f"certify train: {m}", file=sys.stderr,
                                             flush=True))
    if config.preset == "certified":  # counterexample-guided loop (training.certified)
        from training.certified import run_certified

        return run_certified(args, system, config, out)
    if not quiet:
        print(f"training {system.name} with preset {config.preset}: lam {config.lam:g}, "
              f"{config.points} points, hidden {','.join(map(str, config.hidden))} "
              f"{config.activation}, "
              f"Adam {config.adam_iters} + L-BFGS {config.lbfgs_iters}, seed {config.seed}",
              file=out, flush=True)
    if quiet:
        result = train(system, config)
    elif out.isatty():
        with RichProgress() as bar:
            result = train(system, config, progress=bar)
    else:
        result = train(system, config, progress=PlainProgress(out))
    try:
        sha = checkpoint.save(output, system=system, network=result.network, lam=config.lam,
                              P=np.asarray(config.P), training=result.record())
    except OSError as exc:
        raise CertifyError(f"cannot write checkpoint {output}: {exc.strerror or exc}") from None
    if not quiet:
        f = result.final
        print(f"wrote {output} (sha256 {sha[:12]}) in {result.timings['total']:.1f} s: "
              f"loss {f['total']:.4g} (MPDI {f['mpdi']:.4g}, BC {f['bc']:.4g})",
              file=out, flush=True)
    return 0
