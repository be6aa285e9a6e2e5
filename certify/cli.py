"""The `certify` command line: systems, check, train, run, report.

Exit codes (DESIGN.md): 0 certified, 1 not certified, 2 bad input or usage, 3 inconclusive.
Every user error is one line on stderr, prefixed `certify: error:`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from certify.errors import CertifyError

EXIT_BAD_INPUT = 2


class CliProgress:
    """Progress display: rich spinner on a terminal, one plain line per finished step otherwise."""

    def __init__(self, quiet: bool = False) -> None:
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self._t: dict[str, float] = {}
        self._status = None
        if self.tty and not quiet:
            from rich.console import Console

            self._console = Console(stderr=True)

    def start(self, task: str, total: float | None = None) -> None:
        self._t.setdefault(task, time.perf_counter())
        if self.tty and not self.quiet and self._status is None:
            self._status = self._console.status(f"{task} ...")
            self._status.start()
        elif self._status is not None:
            self._status.update(f"{task} ...")

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None:
        if self._status is not None and fields:
            info = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                             for k, v in fields.items())
            self._status.update(f"{task}: {info}")

    def finish(self, task: str, message: str = "") -> None:
        t0 = self._t.pop(task, None)
        if self.quiet or t0 is None or not message:
            return
        line = f"  {task:<12} {message:<9} {time.perf_counter() - t0:7.1f} s"
        if self._status is not None:
            self._console.print(line)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._status is not None:
            self._status.stop()
            self._status = None


# ----- commands ----------------------------------------------------------------------------
def cmd_systems(args: argparse.Namespace) -> int:
    from certify.system import builtin_names, builtin_text, load_system

    if args.name is None:
        for name in builtin_names():
            s = load_system(name)
            print(f"{name:<10} n={s.n} p={s.p}  {s.description}")
        return 0
    system = load_system(args.name)
    if args.name in builtin_names():
        print(builtin_text(args.name).rstrip())
    else:
        print(system.source.rstrip())
    print(f"# Jf = {system.jf_expr.tolist()}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from certify.checks.metric import synthesize_metric
    from certify.checks.necessary import check_necessary
    from certify.system import load_system, parse_metric, validate_metric

    system = load_system(args.system)
    lam = system.lam if args.lam is None else args.lam
    if not lam > 0:
        raise CertifyError(f"--lam must be > 0; got {lam}")
    P = system.P if args.metric is None else validate_metric(
        parse_metric(args.metric, system.n), system.n, "--metric")
    result = check_necessary(system, P, lam)
    out: dict[str, Any] = {"necessary": result}
    print(f"pre-flight necessary condition for {system.name}, lam={lam:g}, P={P.tolist()}:")
    print(f"  {result.status.value}: {result.message}")
    if result.rate_cap is not None:
        print(f"  rate cap for any gain with exact BC: lam_cert <= {result.rate_cap:.4g}")
    if result.residual_price is not None:
        print(f"  price in residual if D <= 0 everywhere: eps_bar >= {result.residual_price:.4g}")
    if result.explanation:
        print("  " + result.explanation)
    code = 0
    if result.status.value != "PROVED" and not args.no_synthesis:
        print(f"searching a constant metric P (SDP, margin {args.margin:g}) ...")
        metric = synthesize_metric(system, lam, margin=args.margin)
        out["metric"] = metric
        print(f"  {metric.status.value}: {metric.message}")
        if metric.P is not None:
            print(f"  P = {json.dumps([[round(v, 6) for v in row] for row in metric.P])}  "
                  f"(cond {metric.condition_number:.4g})")
            print(f"  use it: certify check {args.system} --lam {lam:g} --metric "
                  f"'{json.dumps(metric.P)}'")
        code = 0 if metric.status.value == "PROVED" else 1
    elif result.status.value == "VIOLATED":
        code = 1
    if args.json:
        from certify.checkpoint import atomic_write_bytes
        from certify.results import to_jsonable

        atomic_write_bytes(args.json, json.dumps(to_jsonable(out), indent=1).encode())
    return code


def _flag_settings(args: argparse.Namespace) -> dict[str, Any]:
    def csv(value: str | None) -> tuple[str, ...] | None:
        return None if value is None else tuple(x.strip() for x in value.split(",") if x.strip())

    return {
        "grid_points": args.grid_points, "proof_seconds": args.proof_seconds,
        "max_boxes": args.max_boxes, "noise": args.noise, "seed": args.seed,
        "required": csv(args.require), "skip": csv(args.skip),
        "allow_unknown": True if args.allow_unknown else None, "sim_time": args.sim_time,
        "adversarial_starts": args.adversarial_starts,
    }


def cmd_run(args: argparse.Namespace) -> int:
    from certify import checkpoint as ckpt_mod
    from certify.certificate import exit_code
    from certify.config import load_settings
    from certify.verify import verify

    settings, config_path = load_settings(
        _flag_settings(args), Path(args.config) if args.config else None,
        use_pyproject=not args.no_config)
    ckpt = ckpt_mod.load(args.checkpoint)
    if not args.quiet:
        print(f"certify run {args.checkpoint}: system {ckpt.problem.system.name}, lam="
              f"{ckpt.problem.lam:g}, sha256 {ckpt.sha256[:12]}"
              + (f", policy from {config_path}" if config_path else ""), file=sys.stderr)
    progress = CliProgress(quiet=args.quiet)
    try:
        cert = verify(ckpt, settings, progress=progress)
    finally:
        progress.close()
    _write_outputs(cert, args)
    if not args.quiet:
        print_summary(cert)
    else:
        print(f"{cert.verdict}: {cert.summary}")
    return exit_code(cert)


def _write_outputs(cert: Any, args: argparse.Namespace) -> None:
    targets = {k: getattr(args, k, None) for k in ("html", "pdf", "junit", "json")}
    if not any(targets.values()):
        return
    from reports.render import write_reports

    write_reports(cert, **targets)


def cmd_report(args: argparse.Namespace) -> int:
    from certify.certificate import Certificate

    cert = Certificate.load(args.certificate)
    if not any(getattr(args, k) for k in ("html", "pdf", "junit", "json")):
        raise CertifyError("nothing to write: give --html, --pdf, --junit or --json")
    _write_outputs(cert, args)
    if not args.quiet:
        print_summary(cert)
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from training.command import run_train

    return run_train(args)


def print_summary(cert: Any, out: Any = None) -> None:
    """The short table of every check (from the reports' content) and the verdict line."""
    from reports.content import check_rows

    out = out or sys.stdout
    rows = [{"check": r.name, "label": r.title, "status": r.status,
             "sampled": r.sampled.value, "proved": r.proved.value, "message": r.message,
             "required": "yes" if r.required else ""} for r in check_rows(cert)]
    if out.isatty():
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"certify: {cert.system.get('name', '')} (lam={cert.lam:g})")
        for col in ("check", "status", "sampled", "proved", "required"):
            table.add_column(col)
        colours = {"PROVED": "green", "PASSED": "green", "VIOLATED": "red",
                   "UNKNOWN": "yellow", "ERROR": "red"}
        for r in rows:
            st = f"[{colours.get(r['status'], 'white')}]{r['status']}[/]"
            table.add_row(r["label"], st, r["sampled"], r["proved"], r["required"])
        console = Console(file=out)
        console.print(table)
        for r in rows:
            console.print(f"  {r['check']}: {r['message']}", highlight=False, markup=False)
        colour = {"CERTIFIED": "green", "NOT CERTIFIED": "red"}.get(cert.verdict, "yellow")
        console.print(f"[bold {colour}]{cert.verdict}[/]: ", end="", highlight=False)
        console.print(cert.summary, highlight=False, markup=False)
        return
    width = max(len(r["label"]) for r in rows) if rows else 10
    print(f"{'check':<{width}}  {'status':<9} {'sampled':>11} {'proved':>11}  req", file=out)
    for r in rows:
        print(f"{r['label']:<{width}}  {r['status']:<9} {r['sampled']:>11} {r['proved']:>11}  "
              f"{r['required']}", file=out)
    for r in rows:
        print(f"  {r['check']}: {r['message']}", file=out)
    print(f"{cert.verdict}: {cert.summary}", file=out)


# ----- parser ------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        self.exit(EXIT_BAD_INPUT, f"certify: error: {message} (see 'certify --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="certify", description="Train and certify learned contraction "
                     "observers. Exit codes of run: 0 certified, 1 not certified, 2 bad input, "
                     "3 inconclusive.")
    parser.add_argument("--version", action="version", version="certify 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("systems", help="list built-in systems, or print one spec")
    p.add_argument("name", nargs="?", help="a built-in name or a spec path")
    p.set_defaults(func=cmd_systems)

    p = sub.add_parser("check", help="pre-flight: necessary condition and metric synthesis")
    p.add_argument("system", help="built-in name or spec path")
    p.add_argument("--lam", type=float, help="contraction rate (default: the spec's)")
    p.add_argument("--metric", help="metric P as [[a,b],[b,c]] (default: the spec's)")
    p.add_argument("--margin", type=float, default=0.05, help="SDP margin (default 0.05)")
    p.add_argument("--no-synthesis", action="store_true", help="do not search a metric")
    p.add_argument("--json", help="write the results as JSON")
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("train", help="train a gain network and write a checkpoint")
    from training.command import add_train_arguments

    add_train_arguments(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("run", help="verify a checkpoint and write the certificate")
    p.add_argument("checkpoint")
    for name in ("html", "pdf", "json", "junit"):
        p.add_argument(f"--{name}", metavar="PATH", help=f"write the {name.upper()} report")
    p.add_argument("--grid-points", type=int, help="dense grid size over X x Y (default 1e6)")
    p.add_argument("--proof-seconds", type=float, help="prover time budget (default 60)")
    p.add_argument("--max-boxes", type=int, help="prover sub-box budget")
    p.add_argument("--adversarial-starts", type=int, help="gradient-ascent starts")
    p.add_argument("--noise", type=float, help="noise bound vbar (default 0.15)")
    p.add_argument("--sim-time", type=float, help="simulated seconds (default 10)")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--require", help="comma-separated checks that must pass (default mpdi)")
    p.add_argument("--skip", help="comma-separated checks not to run")
    p.add_argument("--allow-unknown", action="store_true",
                   help="an UNKNOWN required check does not fail the gate")
    p.add_argument("--config", help="read [tool.certify] from this file")
    p.add_argument("--no-config", action="store_true", help="ignore pyproject.toml")
    p.add_argument("--quiet", "-q", action="store_true", help="only the verdict line")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("report", help="re-render reports from a saved JSON certificate")
    p.add_argument("certificate")
    for name in ("html", "pdf", "json", "junit"):
        p.add_argument(f"--{name}", metavar="PATH", help=f"write the {name.upper()} report")
    p.add_argument("--quiet", "-q", action="store_true")
    p.set_defaults(func=cmd_report)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors (exit 2), --help and --version (exit 0)
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_BAD_INPUT
    try:
        return int(args.func(args))
    except CertifyError as exc:
        print(f"certify: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("certify: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
