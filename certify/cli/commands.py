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
from certify.files import stage_file
from certify.spec import builtin

#: the report flags of `run` and `report`, and which of them may name stdout ("-")
REPORT_FLAGS = ("html", "pdf", "json", "junit")
STDOUT = "-"


# ----- inputs and outputs ---------------------------------------------------------------
def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether paths `a` and `b` name one file: the same inode where both exist (hard links,
    symbolic links, `./x` and `../dir/x`, a case-insensitive file system), else the same
    resolved path (symbolic links followed, `.` and `..` removed)."""
    try:
        if os.path.samefile(a, b):
            return True
    except OSError:  # one of them does not exist (yet)
        pass
    return os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b))


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


def check_paths(outputs: list[tuple[str, str | None]],
                inputs: list[tuple[str, str | Path | None]] = (),  # type: ignore[assignment]
                *, stdout_ok: tuple[str, ...] = ("--json",)) -> None:
    """The one check of a command's files, before any work: every output (flag, path) that is
    set must not be any input (what, path), nor another output, and must be creatable.

    Inputs are never overwritten: an output that is the checkpoint, the model, the spec, the
    policy file or the certificate being read is refused (one line, exit 2), whatever path
    names it. `-` (stdout, for the flags in `stdout_ok`) is not a file.
    """
    named = [(flag, str(path)) for flag, path in outputs if path is not None]
    given = [(what, path) for what, path in inputs if path is not None]
    seen: list[tuple[str, str]] = []
    for flag, path in named:
        if path != STDOUT:
            for what, source in given:
                if same_file(path, source):
                    raise CertifyError(f"{flag} {path}: is {what} ({source}); an input is "
                                       "never overwritten: name a new file")
        check_output_path(path, flag, allow_stdout=flag in stdout_ok)
        if path == STDOUT:
            continue
        for other_flag, other in seen:
            if same_file(path, other):
                raise CertifyError(f"{flag} {path}: the same file is already the "
                                   f"{other_flag} output")
        seen.append((flag, path))


def report_outputs(args: argparse.Namespace) -> list[tuple[str, str | None]]:
    """The report flags of `run` and `report` as (flag, path)."""
    return [(f"--{flag}", getattr(args, flag, None)) for flag in REPORT_FLAGS]


def system_argument(value: str) -> Path | None:
    """What a system argument names, decided as `certify.spec.system.load_system` decides it but
    without importing it (an unknown name is a cheap error, so it must be a fast one): None
    for a built-in name, the spec's path for a file; `SpecError` for anything else, with the
    closest built-in name when the value looks like a typo of one."""
    from certify.errors import SpecError

    names = builtin.names()
    if value in names:
        return None
    path = Path(value)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise SpecError(f"spec file {value} not found")
        return path
    import difflib

    close = difflib.get_close_matches(value, names, n=1, cutoff=0.6)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    raise SpecError(f"unknown system '{value}'{hint} (built-ins: {', '.join(names)}; or give "
                    "the path of a .toml spec)")


def commit_files(contents: dict[str, bytes]) -> None:
    """Write every file of `contents` (path -> bytes) or none: each is staged beside its
    target first, then all are renamed into place together.

    Interrupts (Ctrl-C) are held back throughout (`certify.cli.interrupts.INTERRUPTS.deferred`) and
    looked at between files: one that came while staging, including one Python dropped
    inside a finaliser while the reports were drawn, removes the staged files and touches no
    target; one during the renames lets them finish. Each target is therefore the file it
    was before or the complete new one, no temporary file is left, and the interrupt is
    raised at the end either way.
    """
    from certify.cli.interrupts import INTERRUPTS

    staged: list[tuple[str, str]] = []
    with INTERRUPTS.deferred():
        try:
            for path, data in contents.items():
                if INTERRUPTS.received:
                    raise KeyboardInterrupt
                staged.append((stage_file(path, data), path))
            if INTERRUPTS.received:
                raise KeyboardInterrupt
            for tmp, path in staged:
                os.replace(tmp, path)
        except BaseException:
            for tmp, _ in staged:
                Path(tmp).unlink(missing_ok=True)
            raise
    INTERRUPTS.check()


def human_stream(args: argparse.Namespace) -> TextIO:
    """Where summaries go: stdout, unless the JSON report is written there."""
    return sys.stderr if getattr(args, "json", None) == STDOUT else sys.stdout


# ----- systems ----------------------------------------------------------------------------
def cmd_systems(args: argparse.Namespace) -> int:
    """List the built-in systems, or print one with its Jacobian.

    The list, a built-in system and an unknown name are answered from the spec files and
    sympy alone (torch is not imported: these are the quick answers); a user's spec file is
    loaded and validated in full (`certify.spec.system.load_system`).
    """
    from certify.cli.config import tomllib

    names = builtin.names()
    if args.name is None:
        for name in names:
            spec = tomllib.loads(builtin_spec_text(name))
            print(f"{name:<10} n={len(spec.get('states', []))} "
                  f"p={len(spec.get('outputs', []))}  {spec.get('description', '')}")
        return 0
    path = system_argument(args.name)
    if path is None:
        text = builtin_spec_text(args.name)
        print(text.rstrip())
        print(f"# Jf = {spec_jacobian(tomllib.loads(text))}")
        return 0
    from certify.spec.system import load_system

    system = load_system(path)
    print(system.source.rstrip())
    print(f"# Jf = {system.jf_expr.tolist()}")
    return 0


def builtin_spec_text(name: str) -> str:
    """The TOML text of a built-in system."""

    return builtin.text(name)


def spec_jacobian(spec: dict[str, Any]) -> list[list[Any]]:
    """Jf of a (shipped, already validated) spec, by the same parser and sympy calls as
    `certify.spec.system.System`, without importing the rest of it (torch)."""
    import sympy

    from certify.spec.parse import parse_expression

    symbols = {s: sympy.Symbol(s, real=True) for s in spec["states"]}
    f = [parse_expression(text, symbols, f"f[{i}]") for i, text in enumerate(spec["f"])]
    x = sympy.Matrix([symbols[s] for s in spec["states"]])
    return sympy.Matrix(f).jacobian(x).tolist()


# ----- check ------------------------------------------------------------------------------
def cmd_check(args: argparse.Namespace) -> int:
    """Pre-flight of a spec as given: 0 passes, 1 fails (with the metric that would fix it
    when one is found), 3 undecided."""
    check_paths([("--json", args.json)], [("the spec being checked",
                                            system_argument(args.system))])
    from certify.checks.necessary import check_necessary
    from certify.design.metric import synthesize_metric
    from certify.results import Status, to_jsonable
    from certify.spec.system import load_system, parse_metric, validate_lam, validate_metric

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
    given = [flag for flag, v in (("--lam", args.lam), ("--metric", args.metric)) if v]
    what = "the spec as given" if not given else f"the spec with {' and '.join(given)}"
    print(f"{what} {verdict} the pre-flight (exit {code})", file=out)
    if args.json:
        _write_json(args.json, json.dumps(to_jsonable(record), indent=1) + "\n")
    return code


def _write_json(path: str, text: str) -> None:
    if path == STDOUT:
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    commit_files({path: text.encode("utf-8")})


# ----- train ------------------------------------------------------------------------------
def cmd_train(args: argparse.Namespace) -> int:
    from training.command import resolve_system, run_train

    resolve_system(args)
    check_paths([("-o", args.output)], [("the spec being trained for",
                                         system_argument(args.system))])
    return run_train(args)


# ----- import -----------------------------------------------------------------------------
def cmd_import(args: argparse.Namespace) -> int:
    """A model trained elsewhere (ONNX, TorchScript, state_dict) -> a normal checkpoint."""
    if args.system is None:
        raise CertifyError("certify import needs --system SPEC (the system the model observes)")
    check_paths([("-o", args.output)], [("the model being imported", args.model),
                                        ("the --system spec", system_argument(args.system))])
    from certify.cli.importing import run_import

    return run_import(args)


# ----- run, report ------------------------------------------------------------------------
def _flag_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The settings the options of `certify run` set (`certify.cli.config.FLAGS`, made from
    the declarations): None where an option was not given."""
    from certify.cli.config import FLAGS

    return {name: getattr(args, name, None) for name in FLAGS}


def _names(values: list[str] | None) -> tuple[str, ...] | None:
    """A repeated, comma-separated option (--skip a --skip b,c) as one tuple of names."""
    from certify.settings import split_names

    return None if values is None else tuple(n for v in values for n in split_names(v))


def _check_policy_flags(args: argparse.Namespace) -> None:
    """--require and --skip in the words of the flags: the MPDI is the certificate, so it is
    always required and always run (`certify.settings.CERTIFICATE_CHECK`). Unknown names are
    left to the settings' own message."""
    from certify.settings import CERTIFICATE_CHECK, CHECK_NAMES

    required, skip = _names(args.required), _names(args.skip)
    if required is not None and CERTIFICATE_CHECK not in required \
            and set(required) <= set(CHECK_NAMES):
        others = ",".join(c for c in required if c != CERTIFICATE_CHECK)
        raise CertifyError(f"--require {','.join(required)!r}: the MPDI is the certificate and "
                           "is always required; name the other checks beside it, e.g. "
                           f"--require {','.join(filter(None, (CERTIFICATE_CHECK, others)))}")
    if skip is not None and CERTIFICATE_CHECK in skip:
        raise CertifyError(f"--skip {','.join(skip)}: the MPDI is the certificate and always "
                           "runs; bound its work with --max-boxes instead")


def _run_inputs(args: argparse.Namespace) -> list[tuple[str, str | Path | None]]:
    """The files `certify run` reads: the checkpoint (or model), the --system spec, and the
    policy file (--config, else the pyproject.toml found, unless --no-config)."""
    from certify.cli.config import find_pyproject

    model = args.system is not None
    inputs: list[tuple[str, str | Path | None]] = [
        (f"the {'model' if model else 'checkpoint'} being verified", args.checkpoint)]
    if model:
        inputs.append(("the --system spec", system_argument(args.system)))
    if args.config:
        inputs.append(("the --config file", args.config))
    elif not args.no_config:
        inputs.append(("the pyproject.toml the policy is read from", find_pyproject()))
    return inputs


def _design_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """--lam and --metric on a checkpoint: the design values verified instead of its own
    (`certify.verify.verify(overrides=...)`), validated as far as they can be before the
    checkpoint is read (the metric's size is checked against it after); the options that
    only a model from elsewhere takes are refused here."""
    if args.system is not None:  # a model from elsewhere: they are its design values
        return {}
    only_model = [flag for flag in ("--activation", "--structure")
                  if getattr(args, flag[2:], None) is not None]
    if only_model:
        raise CertifyError(f"{', '.join(only_model)}: only for a model from elsewhere, given "
                           "with --system SPEC (a checkpoint carries its own)")
    from certify.spec.system import parse_metric, validate_lam

    out: dict[str, Any] = {}
    if args.lam is not None:
        out["lam"] = validate_lam(args.lam, "--lam")
    if args.metric is not None:
        out["metric"] = parse_metric(args.metric)
    return out


def cmd_run(args: argparse.Namespace) -> int:
    """Verify a checkpoint; write the reports asked for; exit with the verdict's code.

    Everything that can be refused from the arguments alone (paths, a missing input, an
    unknown system, the policy, every option's value) is refused before the checkpoint is
    read. Without a report output the run stops once the verdict is decided (`fail_fast`:
    a required check VIOLATED)."""
    check_paths(report_outputs(args), _run_inputs(args))
    if not Path(args.checkpoint).exists():
        what = "model" if args.system is not None else "checkpoint"
        raise CertifyError(f"{what} {args.checkpoint} not found")
    _check_policy_flags(args)
    from certify.cli.config import load_settings
    from certify.cli.display import ProgressDisplay

    settings, config_path = load_settings(
        _flag_settings(args), Path(args.config) if args.config else None,
        use_pyproject=not args.no_config)
    overrides = _design_overrides(args)
    from certify.arith.device import resolve_device
    from certify.certificate import exit_code
    from certify.cli.importing import checkpoint_for_run
    from certify.cli.interrupts import INTERRUPTS
    from certify.search.distributed.executor import executor_from_settings
    from certify.verify import verify

    resolve_device(settings.device)  # bad device or scheduler: exit 2 before any work
    ckpt = checkpoint_for_run(args)
    if "metric" in overrides:
        from certify.spec.system import validate_metric

        n = ckpt.problem.n
        overrides["metric"] = validate_metric(overrides["metric"], n, "--metric")
    executor = executor_from_settings(settings)
    wants_reports = any(getattr(args, k) for k in REPORT_FLAGS)
    try:
        if not args.quiet:
            lam = overrides.get("lam", ckpt.problem.lam)
            given = (f" (override; checkpoint {ckpt.problem.lam:g})" if "lam" in overrides
                     else "")
            print(f"certify run {args.checkpoint}: system {ckpt.problem.system.name}, lam="
                  f"{lam:g}{given}, sha256 {ckpt.sha256[:12]}"
                  + (", metric overridden" if "metric" in overrides else "")
                  + (f", policy from {config_path}" if config_path else "")
                  + (f", on {executor.description}" if executor.remote else ""),
                  file=sys.stderr)
        display = ProgressDisplay(quiet=args.quiet, interrupted=INTERRUPTS.check)
        args.display = display  # the error handler names the step that was running
        try:
            wants_figures = any(getattr(args, k) for k in ("html", "pdf", "json"))
            cert = verify(ckpt, settings, progress=display, figures=wants_figures,
                          executor=executor, fail_fast=not wants_reports,
                          overrides=overrides)
            INTERRUPTS.check()  # one Python dropped inside a finaliser during the checks
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
    check_paths(report_outputs(args), [("the certificate being re-rendered", args.certificate)])
    from certify.certificate import Certificate
    from certify.cli.display import ProgressDisplay

    cert = Certificate.load(args.certificate)
    if getattr(args, "trajectories", False) and not args.quiet and not _has_states(cert):
        from reports.figures_sim import NO_STATES

        print(f"certify: note: {NO_STATES}", file=sys.stderr)
    display = ProgressDisplay(quiet=args.quiet)
    args.display = display
    try:
        write_outputs(cert, args, display)
    finally:
        display.close()
    _summary(cert, args)
    return 0


def _has_states(cert: Any) -> bool:
    """Whether the certificate holds simulated states (written only with --trajectories)."""
    sim = cert.checks.get("simulation")
    return any(run.x for run in getattr(sim, "runs", None) or [])


def write_outputs(cert: Any, args: argparse.Namespace, display: Any) -> None:
    """Write the reports asked for, as one step ("reports") of the progress display: all
    rendered in memory, then written together or not at all (`commit_files`)."""
    targets = {k: getattr(args, k, None) for k in REPORT_FLAGS if getattr(args, k, None)}
    if not targets:
        return
    display.start_step("reports")
    t0 = time.perf_counter()
    files = {k: path for k, path in targets.items() if path != STDOUT}
    if files:
        from reports.render import render_reports

        data = render_reports(cert, trajectories=bool(getattr(args, "trajectories", False)),
                              **{k: True for k in files})
        commit_files({path: data[k] for k, path in files.items()})
    if targets.get("json") == STDOUT:
        _write_json(STDOUT, cert.to_json(trajectories=bool(getattr(args, "trajectories", False)))
                    + "\n")
    display.finish_step("reports", "written", time.perf_counter() - t0)


def _summary(cert: Any, args: argparse.Namespace) -> None:
    from certify.cli.display import print_verdict

    out = human_stream(args)
    if args.quiet:  # the verdict line and the error bound on the line after it
        print_verdict(cert, out)
    else:
        print_summary(cert, out)


def print_summary(cert: Any, out: TextIO | None = None) -> None:
    """The short table of every check, the table of simulation runs and the verdict line."""
    from certify.cli.display import print_summary as show

    show(cert, out or sys.stdout)


# ----- completion -------------------------------------------------------------------------
def cmd_completion(args: argparse.Namespace) -> int:
    from certify.cli.completion import completion_script
    from certify.cli.parser import build_parser

    sys.stdout.write(completion_script(build_parser(with_train=True), args.shell))
    return 0
