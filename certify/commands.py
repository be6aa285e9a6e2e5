"""The commands behind `certify systems | check | train | run | report | completion`.

Each takes the parsed arguments and returns an exit code; bad input raises `CertifyError`
(one line, exit 2). Output paths are checked before any work starts, and heavy libraries
(torch, sympy, cvxpy, matplotlib) are imported only by the commands that need them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, TextIO

from certify.errors import CertifyError

#: the report flags of `run` and `report`, and which of them may name stdout ("-")
REPORT_FLAGS = ("html", "pdf", "json", "junit")
STDOUT = "-"


# ----- output paths ---------------------------------------------------------------------
def check_output_path(path: str, flag: str, *, allow_stdout: bool = False) -> None:
    """Refuse, before any work, an output path whose file cannot be created.

    The directory must exist and accept a new file (probed by creating and removing a
    temporary file there, which also catches read-only file systems and /proc); the path
    must not be a directory. `-` means stdout where `allow_stdout`.
    """
    if path == STDOUT:
        if allow_stdout:
            return
        raise CertifyError(f"{flag} {path}: writing to stdout is supported only for --json")
    target = Path(path)
    if target.is_dir():
        raise CertifyError(f"{flag} {path}: is a directory, not a file")
    folder = target.parent
    if not folder.exists():
        raise CertifyError(f"{flag} {path}: directory {folder} does not exist")
    if not folder.is_dir():
        raise CertifyError(f"{flag} {path}: {folder} is not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise CertifyError(f"{flag} {path}: cannot create a file in {folder} "
                           f"({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(probe)


def check_outputs(args: argparse.Namespace, flags: tuple[str, ...]) -> None:
    """Check every output flag of `args` that is set; the same file may not be named twice."""
    seen: dict[str, str] = {}
    for flag in flags:
        path = getattr(args, flag, None)
        if path is None:
            continue
        check_output_path(path, f"--{flag}", allow_stdout=flag == "json")
        key = path if path == STDOUT else os.path.realpath(path)
        if key in seen:
            raise CertifyError(f"--{flag} {path}: the same file is already the "
                               f"--{seen[key]} output")
        seen[key] = flag


def human_stream(args: argparse.Namespace) -> TextIO:
    """Where summaries go: stdout, unless the JSON report is written there."""
    return sys.stderr if getattr(args, "json", None) == STDOUT else sys.stdout


# ----- systems ----------------------------------------------------------------------------
def cmd_systems(args: argparse.Namespace) -> int:
    """List the built-in systems (read from their TOML files, nothing built), or print one."""
    if args.name is None:
        from importlib import resources

        from certify.config import tomllib

        folder = resources.files("certify") / "systems"
        for entry in sorted(folder.iterdir(), key=lambda p: p.name):
            if not entry.name.endswith(".toml"):
                continue
            spec = tomllib.loads(entry.read_text())
            print(f"{entry.name[:-5]:<10} n={len(spec.get('states', []))} "
                  f"p={len(spec.get('outputs', []))}  {spec.get('description', '')}")
        return 0
    from certify.system import builtin_names, builtin_text, load_system

    system = load_system(args.name)
    if args.name in builtin_names():
        print(builtin_text(args.name).rstrip())
    else:
        print(system.source.rstrip())
    print(f"# Jf = {system.jf_expr.tolist()}")
    return 0


# ----- check ------------------------------------------------------------------------------
def cmd_check(args: argparse.Namespace) -> int:
    """Pre-flight of a spec as given: 0 passes, 1 fails (with the metric that would fix it
    when one is found), 3 undecided."""
    check_outputs(args, ("json",))
    from certify.checks.metric import synthesize_metric
    from certify.checks.necessary import check_necessary
    from certify.results import Status, to_jsonable
    from certify.system import load_system, parse_metric, validate_lam, validate_metric

    out = human_stream(args)
    system = load_system(args.system)
    lam = system.lam if args.lam is None else validate_lam(args.lam, "--lam")
    P = system.P if args.metric is None else validate_metric(
        parse_metric(args.metric, system.n), system.n, "--metric")
    result = check_necessary(system, P, lam)
    record: dict[str, Any] = {"necessary": result}
    print(f"pre-flight necessary condition for {system.name}, lam={lam:g}, P={P.tolist()}:",
          file=out)
    print(f"  {result.status.value}: {result.message}", file=out)
    if result.rate_cap is not None:
        print(f"  rate cap for any gain with exact BC: lam_cert <= {result.rate_cap:.4g}",
              file=out)
    if result.residual_price is not None:
        print(f"  price in residual if D <= 0 everywhere: eps_bar >= "
              f"{result.residual_price:.4g}", file=out)
    if result.explanation:
        print("  " + result.explanation, file=out)
    code = {Status.PROVED: 0, Status.VIOLATED: 1}.get(result.status, 3)
    if result.status != Status.PROVED and not args.no_synthesis:
        print(f"searching a constant metric P (SDP, margin {args.margin:g}) ...", file=out)
        metric = synthesize_metric(system, lam, margin=args.margin)
        record["metric"] = metric
        print(f"  {metric.status.value}: {metric.message}", file=out)
        if metric.P is not None:
            print(f"  P = {json.dumps([[round(v, 6) for v in row] for row in metric.P])}  "
                  f"(cond {metric.condition_number:.4g})", file=out)
            if metric.status == Status.PROVED:
                print(f"  fix: certify check {args.system} --lam {lam:g} --metric "
                      f"'{json.dumps(metric.P)}'", file=out)
    verdict = {0: "passes", 1: "fails", 3: "is undecided"}[code]
    print(f"the spec as given {verdict} the pre-flight (exit {code})", file=out)
    if args.json:
        _write_json(args.json, json.dumps(to_jsonable(record), indent=1) + "\n")
    return code


def _write_json(path: str, text: str) -> None:
    if path == STDOUT:
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    from certify.checkpoint import atomic_write_bytes

    atomic_write_bytes(path, text.encode("utf-8"))


# ----- train ------------------------------------------------------------------------------
def cmd_train(args: argparse.Namespace) -> int:
    check_output_path(args.output, "-o")
    from training.command import run_train

    return run_train(args)


# ----- import -----------------------------------------------------------------------------
def cmd_import(args: argparse.Namespace) -> int:
    """A model trained elsewhere (ONNX, TorchScript, state_dict) -> a normal checkpoint."""
    if args.system is None:
        raise CertifyError("certify import needs --system SPEC (the system the model observes)")
    check_output_path(args.output, "-o")
    if os.path.realpath(args.output) == os.path.realpath(args.model):
        raise CertifyError(f"-o {args.output}: is the model itself; name a new checkpoint")
    from certify.importers.command import run_import

    return run_import(args)


# ----- run, report ------------------------------------------------------------------------
def _flag_settings(args: argparse.Namespace) -> dict[str, Any]:
    def csv(value: str | None) -> tuple[str, ...] | None:
        return None if value is None else tuple(x.strip() for x in value.split(",") if x.strip())

    return {
        "grid_points": args.grid_points, "proof_seconds": args.proof_seconds,
        "max_boxes": args.max_boxes, "noise": args.noise, "seed": args.seed,
        "required": csv(args.require), "skip": csv(args.skip),
        "allow_unknown": True if args.allow_unknown else None, "sim_time": args.sim_time,
        "adversarial_starts": args.adversarial_starts,
        "workers": getattr(args, "workers", None), "scheduler": getattr(args, "scheduler", None),
        "device": getattr(args, "device", None),
    }


def cmd_run(args: argparse.Namespace) -> int:
    """Verify a checkpoint; write the reports asked for; exit with the verdict's code."""
    check_outputs(args, REPORT_FLAGS)
    from certify.config import load_settings
    from certify.display import ProgressDisplay, budgets_from

    settings, config_path = load_settings(
        _flag_settings(args), Path(args.config) if args.config else None,
        use_pyproject=not args.no_config)
    from certify.certificate import exit_code
    from certify.device import resolve_device
    from certify.executor import executor_from_settings
    from certify.importers.command import checkpoint_for_run
    from certify.verify import verify

    resolve_device(settings.device)  # bad device or scheduler: exit 2 before any work
    ckpt = checkpoint_for_run(args)
    executor = executor_from_settings(settings)
    try:
        if not args.quiet:
            print(f"certify run {args.checkpoint}: system {ckpt.problem.system.name}, lam="
                  f"{ckpt.problem.lam:g}, sha256 {ckpt.sha256[:12]}"
                  + (f", policy from {config_path}" if config_path else "")
                  + (f", on {executor.description}" if executor.remote else ""),
                  file=sys.stderr)
        display = ProgressDisplay(quiet=args.quiet, budgets=budgets_from(settings))
        args.display = display  # the error handler names the step that was running
        try:
            wants_figures = any(getattr(args, k) for k in ("html", "pdf", "json"))
            cert = verify(ckpt, settings, progress=display, figures=wants_figures,
                          executor=executor)
            write_outputs(cert, args, display)
        finally:
            display.close()
    finally:
        executor.close()
    _summary(cert, args)
    return exit_code(cert)


def cmd_report(args: argparse.Namespace) -> int:
    """Re-render reports from a saved JSON certificate (no verification)."""
    if not any(getattr(args, k) for k in REPORT_FLAGS):
        raise CertifyError("nothing to write: give --html, --pdf, --junit or --json")
    check_outputs(args, REPORT_FLAGS)
    from certify.certificate import Certificate
    from certify.display import ProgressDisplay

    cert = Certificate.load(args.certificate)
    display = ProgressDisplay(quiet=args.quiet)
    args.display = display
    try:
        write_outputs(cert, args, display)
    finally:
        display.close()
    _summary(cert, args)
    return 0


def write_outputs(cert: Any, args: argparse.Namespace, display: Any) -> None:
    """Write the reports asked for, as one step ("reports") of the progress display."""
    targets = {k: getattr(args, k, None) for k in REPORT_FLAGS}
    if not any(targets.values()):
        return
    display.start_step("reports")
    t0 = time.perf_counter()
    to_stdout = targets.get("json") == STDOUT
    if to_stdout:
        targets["json"] = None
    if any(targets.values()):
        from reports.render import write_reports

        write_reports(cert, **targets, trajectories=bool(getattr(args, "trajectories", False)))
    if to_stdout:
        _write_json(STDOUT, cert.to_json() + "\n")
    display.finish_step("reports", "written", time.perf_counter() - t0)


def _summary(cert: Any, args: argparse.Namespace) -> None:
    from reports.content import verdict_line

    out = human_stream(args)
    if args.quiet:
        print(verdict_line(cert), file=out)
    else:
        print_summary(cert, out)


def print_summary(cert: Any, out: TextIO | None = None) -> None:
    """The short table of every check, the table of simulation runs and the verdict line."""
    from certify.display import print_summary as show

    show(cert, out or sys.stdout)


# ----- completion -------------------------------------------------------------------------
def cmd_completion(args: argparse.Namespace) -> int:
    from certify.cli import build_parser
    from certify.completion import completion_script

    sys.stdout.write(completion_script(build_parser(with_train=True), args.shell))
    return 0
