"""The argument parser of `certify`: commands, flags, help texts (built from the registries).

The settings options of `certify run` are made from the declarations of
`certify.settings.DECLARATIONS` (`add_setting_options`): flag, type, help and default each
come from there, and the options of retired settings (`certify.settings.RETIRED`) are
refused with their replacement. Building it imports only the standard library and the light
parts of certify (settings, the built-in spec names), so `certify --help` and the one-line
usage errors answer at once; the `train` command's own options come from `training.command`
only when the command is `train`.
"""

from __future__ import annotations

import argparse
from typing import Any

from certify.certificate import EXIT_BAD_INPUT
from certify.settings import (
    CHECK_NAMES,
    DECLARATIONS,
    RETIRED,
    Checks,
    Count,
    Number,
    Switch,
    flag_of,
    retired_message,
)
from certify.spec import builtin

EXIT_CODES_TEXT = ("exit codes of run: 0 certified, 1 not certified, 2 bad input or usage, "
                   "3 inconclusive (a required check unknown or in ERROR), 4 internal error; "
                   "any command: 130 interrupted, 141 output pipe closed")

EXAMPLES = """\
examples:
  certify systems                                   list the built-in systems
  certify check vdp                                 pre-flight the spec as given
  certify train vdp --preset certified -o vdp.ckpt  train a gain network
  certify run vdp.ckpt --html r.html --junit r.xml  verify, write reports
  certify run vdp.ckpt --json - --quiet | jq .verdict
  certify run vdp.ckpt --require rate --skip simulation --skip dissipation
  certify run vdp.ckpt --lam 0.45                   verify at another design rate
  certify run model.onnx --system spec.toml         verify a model trained elsewhere
  certify import model.onnx --system spec.toml -o model.ckpt
  certify report r.json --pdf r.pdf                 re-render without verifying
  eval "$(certify completion bash)"                 tab completion (bash, zsh, fish)

""" + EXIT_CODES_TEXT + "."


def version() -> str:
    """The installed distribution's version (the package's own when not installed)."""
    from importlib import metadata

    try:
        return metadata.version("certify")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare tree
        from certify import __version__

        return __version__



class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        self.exit(EXIT_BAD_INPUT, f"certify: error: {message} (see '{self.prog} --help')\n")


def _report_flags(p: argparse.ArgumentParser, json_help: str) -> None:
    p.add_argument("--html", metavar="PATH", help="write the HTML report")
    p.add_argument("--pdf", metavar="PATH", help="write the PDF report")
    p.add_argument("--json", metavar="PATH", help=json_help)
    p.add_argument("--junit", metavar="PATH",
                   help="write JUnit XML (a required check that fails is a <failure>, ERROR "
                        "an <error>; checks not required never fail the build)")
    p.add_argument("--trajectories", action="store_true",
                   help="also plot each simulated run's true and estimated states (HTML/PDF) and "
                        "store them in the JSON certificate")


def _text_type(rule: Any, flag: str):
    """The argparse `type` of an option with `rule`: its `from_text`, its error as the
    one-line usage error (argparse names the option)."""
    def parse(text: str) -> Any:
        try:
            return rule.from_text(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = flag.lstrip("-")
    return parse


class _Retired(argparse.Action):
    """The option of a retired setting: refused, naming what replaced it."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option: Any = None) -> None:
        parser.error(retired_message(self.dest, "", as_flag=True))


def add_setting_options(p: argparse.ArgumentParser) -> None:
    """The options of `certify run` that set a setting, one per declaration with a `flag`
    (dest: the setting's name; default None, so that [tool.certify] applies where not
    given); a repeated list option (--skip, --require) accumulates. Then the retired
    settings' options, hidden, each refused with its replacement."""
    for d in DECLARATIONS:
        if d.flag is None:
            continue
        given = d.default not in (None, "", ()) and not isinstance(d.rule, Switch)
        default = f" (default {d.default_text()})" if given else ""
        kw: dict[str, Any] = dict(dest=d.name, default=None, help=d.help + default)
        if isinstance(d.rule, Switch):
            kw["action"] = "store_true"
        elif isinstance(d.rule, Checks):
            kw.update(action="append", metavar=d.metavar or "CHECKS")
        else:
            if isinstance(d.rule, (Count, Number)):
                kw["type"] = _text_type(d.rule, d.flag)
            kw["metavar"] = d.metavar or d.name.upper()
        p.add_argument(d.flag, **kw)
    for old in RETIRED:
        p.add_argument(flag_of(old), dest=old, nargs="?", action=_Retired,
                       help=argparse.SUPPRESS)


def systems_text() -> str:
    """The built-in systems, as help text names them (read from the package's spec files)."""
    return ", ".join(builtin.names())


def _model_flags(p: argparse.ArgumentParser, system_help: str, *, run: bool = False) -> None:
    """The flags that turn a model from elsewhere (ONNX, TorchScript, state_dict) into a
    verification problem (`certify import`, `certify run MODEL --system SPEC`); for `run`,
    --lam and --metric also override a checkpoint's own design values."""
    whose = "the checkpoint's or the spec's" if run else "the spec's"
    also = ("; on a checkpoint an override of its own, recorded in the certificate" if run
            else "")
    p.add_argument("--system", metavar="SPEC", help=system_help)
    p.add_argument("--lam", type=float, help=f"design contraction rate (default: {whose}{also})")
    p.add_argument("--metric", help=f"metric P as [[a,b],[b,c]] (default: {whose}{also})")
    p.add_argument("--activation", metavar="NAME",
                   help="the activation of a state_dict (it carries none), e.g. tanh")
    p.add_argument("--structure", choices=("direct", "structural"),
                   help="gain structure when the output width does not decide it (p = 1)")


def build_parser(with_train: bool = True) -> argparse.ArgumentParser:
    """The full parser. `with_train=False` leaves out `train`'s own options (they import
    the training code); `main` builds them only when the command is `train`."""
    formatter = argparse.RawDescriptionHelpFormatter
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        help="on an internal error, print the traceback")
    parser = _Parser(prog="certify", formatter_class=formatter, epilog=EXAMPLES,
                     description="Train and certify learned contraction observers.")
    parser.add_argument("--version", action="version", version=f"certify {version()}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser,
                                metavar="COMMAND")

    systems = systems_text()
    p = sub.add_parser("systems", parents=[common],
                       help=f"list the built-in systems ({systems}), or print one")
    p.add_argument("name", nargs="?", help=f"a built-in name ({systems}) or a spec path")
    p.set_defaults(command="systems")

    p = sub.add_parser("check", parents=[common], formatter_class=formatter,
                       help="pre-flight a spec: necessary condition and metric synthesis",
                       epilog="exit codes: 0 the spec (with --lam, --metric if given) passes, "
                              "1 it fails (a metric that fixes it is printed when one is "
                              "found), 2 bad input, "
                              "3 undecided, 4 internal error.")
    p.add_argument("system", help=f"built-in name ({systems}) or spec path")
    p.add_argument("--lam", type=float, help="contraction rate (default: the spec's)")
    p.add_argument("--metric", help="metric P as [[a,b],[b,c]] (default: the spec's)")
    p.add_argument("--margin", type=float, default=0.05, help="SDP margin (default 0.05)")
    p.add_argument("--no-synthesis", action="store_true", help="do not search a metric")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON ('-': stdout)")
    p.set_defaults(command="check")

    p = sub.add_parser("train", parents=[common],
                       help="train a gain network and write a checkpoint")
    if with_train:
        from training.command import add_train_arguments

        add_train_arguments(p)
    p.set_defaults(command="train")

    names = ", ".join(CHECK_NAMES)
    p = sub.add_parser("run", parents=[common], formatter_class=formatter,
                       help="verify a checkpoint and write the certificate",
                       epilog=f"checks: {names}.\n{EXIT_CODES_TEXT}.")
    p.add_argument("checkpoint", help="a checkpoint written by 'certify train' (.ckpt), or "
                   "a model from elsewhere (.onnx, TorchScript, state_dict) with --system")
    _model_flags(p, f"the system a model from elsewhere observes (built-in name: {systems}; "
                    "or a spec path)", run=True)
    _report_flags(p, "write the JSON certificate ('-': stdout, the rest goes to stderr)")
    add_setting_options(p)
    p.add_argument("--config", metavar="PATH", help="read [tool.certify] from this file")
    p.add_argument("--no-config", action="store_true", help="ignore pyproject.toml")
    p.add_argument("--quiet", "-q", action="store_true", help="only the verdict line")
    p.set_defaults(command="run")

    p = sub.add_parser("import", parents=[common],
                       help="turn an ONNX, TorchScript or state_dict model into a checkpoint")
    p.add_argument("model", help="model.onnx, a TorchScript file, or a state_dict (.pt)")
    _model_flags(p, f"the system the model observes (built-in name: {systems}; or a spec "
                    "path; required)")
    p.add_argument("-o", "--output", required=True, metavar="PATH", help="checkpoint to write")
    p.set_defaults(command="import")

    p = sub.add_parser("report", parents=[common],
                       help="re-render reports from a saved JSON certificate")
    p.add_argument("certificate", help="a JSON certificate written by 'certify run --json'")
    _report_flags(p, "write the JSON certificate again ('-': stdout)")
    p.add_argument("--quiet", "-q", action="store_true", help="only the verdict line")
    p.set_defaults(command="report")

    p = sub.add_parser("completion", parents=[common], formatter_class=formatter,
                       help="print a shell completion script",
                       epilog='bash: eval "$(certify completion bash)"\n'
                              "zsh:  eval \"$(certify completion zsh)\"\n"
                              "fish: certify completion fish | source")
    p.add_argument("shell", choices=("bash", "zsh", "fish"))
    p.set_defaults(command="completion")
    return parser


