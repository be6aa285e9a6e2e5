"""Command-line edges, from the outside where possible: outputs that would overwrite an input,
a policy that drops the certificate, the README's own spec, help generated from the
registries, cheap errors that stay cheap, Ctrl-C at any point, a malformed scheduler, an
absurd worker count and a closed output pipe."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.cli.interrupts import EXIT_INTERRUPTED
from certify.cli.main import EXIT_CLOSED_PIPE, main
from certify.errors import SettingsError
from certify.results import Status
from certify.settings import (
    CHECK_NAMES,
    VerifySettings,
    make_settings,
    max_local_workers,
)

from ..cli_helpers import FAST_POLICY, ROOT, fresh_env, probe, run_cli, save_linear
from ..conftest import LINEAR_SPEC

VDP = ROOT / "examples" / "vdp.ckpt"  # the paper preset: the MPDI is VIOLATED on 100% of X x Y


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (hidden ones included) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _one_error_line(err: str) -> None:
    assert err.startswith("certify: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err


# ----- outputs never overwrite an input ----------------------------------------------------
OVERWRITES = [
    # (argv, the words naming the input)
    (["run", "m.ckpt", "--json", "m.ckpt"], "is the checkpoint being verified"),
    (["run", "m.ckpt", "--html", "./m.ckpt"], "is the checkpoint being verified"),
    (["run", "m.ckpt", "--pdf", "../{dir}/m.ckpt"], "is the checkpoint being verified"),
    (["run", "m.ckpt", "--junit", "link.ckpt"], "is the checkpoint being verified"),  # symlink
    (["run", "m.ckpt", "--json", "hard.ckpt"], "is the checkpoint being verified"),  # hard link
    (["run", "sub/../m.ckpt", "--html", "m.ckpt"], "is the checkpoint being verified"),
    (["run", "model.onnx", "--system", "spec.toml", "--html", "model.onnx"],
     "is the model being verified"),
    (["run", "model.onnx", "--system", "spec.toml", "--json", "spec.toml"],
     "is the --system spec"),
    (["run", "m.ckpt", "--json", "pyproject.toml"], "is the pyproject.toml the policy is read"),
    (["run", "m.ckpt", "--config", "policy.toml", "--junit", "policy.toml"],
     "is the --config file"),
    (["report", "r.json", "--json", "r.json"], "is the certificate being re-rendered"),
    (["report", "r.json", "--html", "./r.json"], "is the certificate being re-rendered"),
    (["check", "spec.toml", "--json", "spec.toml"], "is the spec being checked"),
    (["import", "model.onnx", "--system", "spec.toml", "-o", "model.onnx"],
     "is the model being imported"),
    (["import", "model.onnx", "--system", "spec.toml", "-o", "./spec.toml"],
     "is the --system spec"),
    (["import", "model.onnx", "--system", "vdp", "-o", "hard.onnx"],
     "is the model being imported"),
    (["train", "spec.toml", "-o", "spec.toml"], "is the spec being trained for"),
    # two outputs, one file (the second name a link to the first, existing, output)
    (["run", "m.ckpt", "--html", "out.html", "--pdf", "./out.html"],
     "the same file is already the --html output"),
    (["run", "m.ckpt", "--html", "out.html", "--json", "out-link.html"],
     "the same file is already the --html output"),
]


@pytest.mark.parametrize("argv, words", OVERWRITES)
def test_an_output_onto_an_input_is_exit_2_and_the_input_is_unchanged(workdir, capsys, argv,
                                                                      words):
    """Any output path that resolves to an input (or to another output) is refused before
    any work, whatever names it: `./x`, `../dir/x`, `a/../x`, a symbolic or a hard link."""
    save_linear(workdir / "m.ckpt")
    (workdir / "sub").mkdir()
    (workdir / "link.ckpt").symlink_to(workdir / "m.ckpt")
    os.link(workdir / "m.ckpt", workdir / "hard.ckpt")
    (workdir / "model.onnx").write_bytes(b"\x08\x07crafted onnx bytes")
    os.link(workdir / "model.onnx", workdir / "hard.onnx")
    (workdir / "spec.toml").write_text(LINEAR_SPEC)
    (workdir / "policy.toml").write_text(FAST_POLICY)
    (workdir / "r.json").write_text('{"schema": "certify-certificate"}\n')
    (workdir / "out.html").write_text("an earlier report\n")
    (workdir / "out-link.html").symlink_to(workdir / "out.html")
    before = _snapshot(workdir)
    argv = [a.replace("{dir}", workdir.name) for a in argv]
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, err
    _one_error_line(err)
    assert words in err, err
    assert _snapshot(workdir) == before  # every input byte for byte, nothing new


def test_json_to_stdout_is_not_a_file(workdir, capsys):
    """`--json -` is stdout: never taken for an input or an output file named '-'."""
    (workdir / "-").write_text("a file named '-'\n")
    path = save_linear(workdir / "m.ckpt")
    code, out, err = run_cli(capsys, "run", path, "--json", "-", "--quiet", "--skip",
                             "simulation,lipschitz,rate,residual,bounds")
    assert code == 0, err
    assert json.loads(out)["verdict"] == "CERTIFIED"
    assert (workdir / "-").read_text() == "a file named '-'\n"


# ----- the MPDI is the certificate: always required ------------------------------------
@pytest.mark.parametrize("flags, table, words", [
    (["--require", ""], "", "--require '': the MPDI is the certificate"),
    (["--require", "rate"], "", "e.g. --require mpdi,rate"),
    (["--require", "necessary,residual"], "", "the MPDI is the certificate"),
    (["--skip", "mpdi"], "", "--skip mpdi: the MPDI is the certificate and always runs"),
    (["--skip", "simulation,mpdi"], "", "always runs"),
    ([], "required = []\n", "[tool.certify] required must include mpdi"),
    ([], 'required = ["necessary", "rate"]\n', "[tool.certify] required must include mpdi"),
    ([], 'required = ""\n', "[tool.certify] required must include mpdi"),
    ([], 'skip = ["mpdi"]\n', "[tool.certify] skip cannot include mpdi"),
])
def test_a_policy_without_the_mpdi_is_refused(workdir, capsys, flags, table, words):
    """On the shipped paper-preset checkpoint (MPDI VIOLATED) no policy can certify: one
    without the MPDI is exit 2, one line, nothing written."""
    (workdir / "pyproject.toml").write_text(FAST_POLICY + table)
    code, out, err = run_cli(capsys, "run", str(VDP), "--json", "c.json", "--html", "c.html",
                             *flags)
    assert code == 2, out + err
    _one_error_line(err)
    assert words in err, err
    assert "CERTIFIED" not in out + err
    assert not (workdir / "c.json").exists() and not (workdir / "c.html").exists()


@pytest.mark.slow
def test_a_violated_mpdi_is_not_certified_by_any_accepted_policy(workdir, capsys):
    code, out, _ = run_cli(capsys, "run", str(VDP), "--require", "mpdi,necessary",
                           "--allow-unknown", "--skip", "simulation,lipschitz,rate,residual",
                           "--quiet")
    assert code == 1 and out.startswith("NOT CERTIFIED"), out


@pytest.mark.parametrize("values", [{"required": ()}, {"required": ["rate"]},
                                    {"required": ""}, {"skip": ("mpdi",)}])
def test_library_settings_refuse_dropping_the_mpdi(values):
    with pytest.raises(SettingsError, match="mpdi"):
        make_settings(values)
    with pytest.raises(SettingsError, match="mpdi"):
        VerifySettings(**{k: tuple(v) if isinstance(v, list) else v
                          for k, v in values.items()})


@pytest.mark.slow
def test_verify_never_certifies_a_violated_mpdi_even_with_an_mpdi_less_policy():
    """The library path: settings that bypassed validation (no required check at all, UNKNOWN
    allowed) still give NOT CERTIFIED on the violated example, with the MPDI required."""
    from certify.model import checkpoint
    from certify.verify import verify

    s = VerifySettings(grid_points=20_000, adversarial_starts=4, adversarial_steps=10,
                       allow_unknown=True,
                       skip=("simulation", "lipschitz", "rate", "residual", "bounds"))
    object.__setattr__(s, "required", ())  # what an unchecked policy would hold
    cert = verify(checkpoint.load(VDP), s, figures=False)
    assert cert.checks["mpdi"].status == Status.VIOLATED
    assert cert.verdict == "NOT CERTIFIED" and "mpdi" in cert.required


STATUSES = [Status.PROVED, Status.VIOLATED, Status.UNKNOWN, Status.ERROR, Status.SKIPPED,
            Status.NOT_APPLICABLE, Status.PASSED]


@settings(max_examples=300, deadline=None)
@given(statuses=st.dictionaries(st.sampled_from(CHECK_NAMES), st.sampled_from(STATUSES)),
       required=st.lists(st.sampled_from(CHECK_NAMES), unique=True),
       allow_unknown=st.booleans())
@pytest.mark.slow
def test_certified_always_means_the_mpdi_was_proved(statuses, required, allow_unknown):
    from certify.results import decide_verdict

    checks = {n: types.SimpleNamespace(status=s) for n, s in statuses.items()}
    verdict, summary = decide_verdict(checks, list(required), allow_unknown)
    if verdict == "CERTIFIED":
        assert statuses.get("mpdi") == Status.PROVED, (statuses, required, summary)
    if statuses.get("mpdi") == Status.VIOLATED:
        assert verdict == "NOT CERTIFIED"


def test_allow_unknown_still_waives_the_other_checks():
    from certify.results import decide_verdict

    checks = {"mpdi": types.SimpleNamespace(status=Status.PROVED),
              "rate": types.SimpleNamespace(status=Status.UNKNOWN)}
    assert decide_verdict(checks, ["mpdi", "rate"], True)[0] == "CERTIFIED"
    assert decide_verdict(checks, ["mpdi", "rate"], False)[0] == "INCONCLUSIVE"
    checks["mpdi"] = types.SimpleNamespace(status=Status.UNKNOWN)
    verdict, summary = decide_verdict(checks, ["mpdi", "rate"], True)
    assert verdict == "INCONCLUSIVE" and "must be PROVED" in summary


# ----- the README's spec works as printed --------------------------------------------------
def _readme_pendulum() -> str:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```toml\n(# examples/pendulum\.toml\n.*?)```", text, re.S)
    assert block, "the README's pendulum spec is gone"
    return block.group(1)


@pytest.mark.slow
def test_readme_pendulum_spec_is_the_shipped_example_and_passes(tmp_path, capsys):
    import tomllib

    printed = _readme_pendulum()
    shipped = ROOT / "examples" / "pendulum.toml"
    assert tomllib.loads(printed) == tomllib.loads(shipped.read_text())
    (tmp_path / "pendulum.toml").write_text(printed)  # the README's text, as a user copies it
    for spec in (tmp_path / "pendulum.toml", shipped):
        code, out, _ = run_cli(capsys, "check", str(spec))
        assert code == 0 and "passes the pre-flight (exit 0)" in out, out
    # and what the text says of P = I: it fails, with q = 0.8 and a rate cap of 0.1
    code, out, _ = run_cli(capsys, "check", str(shipped), "--metric", "[[1, 0], [0, 1]]",
                           "--no-synthesis")
    assert code == 1 and "q = 0.8 > 0" in out and "lam_cert <= 0.1" in out, out


# ----- help generated from the registries ----------------------------------------------------
def _help(*argv: str, capsys) -> str:
    assert main([*argv, "--help"]) == 0
    return re.sub(r"\s+", " ", capsys.readouterr().out)


def test_help_lists_every_builtin_system_and_preset(capsys):
    from certify.spec import builtin
    from training.presets import PRESETS, preset_summary

    names = builtin.names()
    assert {"vdp", "duffing", "lorenz", "vdp2", "vdp3"} <= set(names)
    listed = ", ".join(names)
    for argv in (["train"], ["check"], ["systems"], ["run"], ["import"]):
        assert listed in _help(*argv, capsys=capsys), argv
    text = _help("train", capsys=capsys)
    readme = (ROOT / "README.md").read_text()
    for name in PRESETS:
        assert f"{name}: {preset_summary(name)}" in text
        assert re.search(rf'(--preset {name}\b|preset "{name}")', readme), name


def test_device_help_agrees_with_the_readme_and_the_code(capsys):
    text = _help("run", capsys=capsys)
    device = text.split("--device DEVICE torch device", 1)[1].split("--config")[0]
    assert "branch-and-bound proofs (MPDI, rate, residual, dk/dy) run there" in device
    assert "bounds run on the CPU" not in device
    readme = re.sub(r"\s+", " ", (ROOT / "README.md").read_text())
    assert "the adversarial falsifier **and the branch-and-bound proofs** (MPDI, rate, " \
        "residual, local Lipschitz)" in readme
    for check in ("mpdi", "rate", "residual", "lipschitz", "dissipation"):
        # each proof runs on the run's device, resolved once (`Context.on_device`)
        source = (ROOT / "certify" / "checks" / f"{check}.py").read_text()
        assert "context.on_device" in source, check


# ----- cheap errors stay cheap ---------------------------------------------------------------
@pytest.mark.parametrize("argv, heavy_ok, words", [
    (["systems", "vdp"], {"sympy"}, None),
    (["systems", "vpd"], set(), "unknown system 'vpd'; did you mean 'vdp'?"),
    (["systems", "lorenzz"], set(), "did you mean 'lorenz'?"),
    (["systems", "nosuch.toml"], set(), "spec file nosuch.toml not found"),
    (["check", "vpd"], set(), "did you mean 'vdp'?"),
    (["run", str(VDP), "--system", "dufing"], set(), "did you mean 'duffing'?"),
    (["run", "missing.ckpt"], set(), "checkpoint missing.ckpt not found"),
    (["run", "missing.onnx", "--system", "vdp"], set(), "model missing.onnx not found"),
    (["train", "--help"], set(), None),
    (["completion", "bash"], set(), None),
    (["train", "-o", "x.ckpt"], set(), "certify train needs a system"),
    (["train", "vdp", "--system", "lorenz", "-o", "x.ckpt"], set(), "two systems given"),
    (["train", "vpd", "-o", "x.ckpt"], set(), "did you mean 'vdp'?"),
])
@pytest.mark.slow
def test_systems_and_cheap_errors_do_not_import_torch(tmp_path, argv, heavy_ok, words):
    code, out, err, imported = probe(*argv, cwd=tmp_path)
    assert imported is not None and set(imported) <= heavy_ok, imported
    if words is None:
        assert code == 0, err
    else:
        assert code == 2 and words in err, err
        _one_error_line(err)


def test_systems_name_prints_the_spec_and_the_same_jacobian_as_the_full_system(capsys):
    from certify.cli.commands import builtin_spec_text
    from certify.spec import builtin
    from certify.spec.system import load_system

    for name in builtin.names():
        code, out, _ = run_cli(capsys, "systems", name)
        assert code == 0
        assert out.startswith(builtin_spec_text(name).rstrip())
        assert out.rstrip().endswith(f"# Jf = {load_system(name).jf_expr.tolist()}"), name


# ----- Ctrl-C at any point -------------------------------------------------------------------
# Runs certify in a fresh interpreter that sends itself SIGINT at one chosen point: a plain
# interrupt, or one raised inside a finaliser (which Python prints and drops).
INTERRUPTER = r"""
import os, signal, sys
where, argv = sys.argv[1], sys.argv[2:]
TARGETS = ("r.html", "r.json", "r.xml")

def interrupt():
    os.kill(os.getpid(), signal.SIGINT)

class InFinaliser:
    def __del__(self):
        interrupt()

if where.startswith("render"):
    import reports.render as rr
    real_render = rr.render_reports
    def render(*args, **kwargs):
        out = real_render(*args, **kwargs)
        interrupt() if where == "render" else InFinaliser()
        return out
    rr.render_reports = render
elif where == "stage":  # the first report staged, the others not yet
    import certify.cli.commands as cc
    real_stage = cc.stage_file
    def stage(path, data):
        tmp = real_stage(path, data)
        cc.stage_file = real_stage
        interrupt()
        return tmp
    cc.stage_file = stage
elif where == "commit":  # the first report renamed into place, the others not yet
    real_replace = os.replace
    def replace(src, dst):
        if os.path.basename(dst) in TARGETS:
            os.replace = real_replace
            interrupt()
        real_replace(src, dst)
    os.replace = replace
elif where.startswith("check"):
    import certify.checks.registry as registry
    real_one = registry.run_one
    def run_one(check, context, skip=()):
        if check.name == "rate":
            interrupt() if where == "check" else InFinaliser()
        return real_one(check, context, skip)
    registry.run_one = run_one

from certify.cli.main import main
sys.exit(main(argv))
"""


@pytest.mark.parametrize("where", ["check", "check-finaliser", "render", "render-finaliser",
                                   "stage", "commit"])
@pytest.mark.slow
def test_an_interrupt_at_any_point_exits_130_and_leaves_no_partial_report(tmp_path, where):
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    save_linear(tmp_path / "lin.ckpt")
    for name in ("r.html", "r.json"):  # earlier reports: each stays as it was, or is replaced
        (tmp_path / name).write_text("an earlier report\n")
    script = tmp_path / "interrupter.py"
    script.write_text(INTERRUPTER)
    proc = subprocess.run([sys.executable, str(script), where, "run", "lin.ckpt", "--quiet",
                           "--html", "r.html", "--json", "r.json", "--junit", "r.xml",
                           "--skip", "simulation,lipschitz"],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path,
                          env=fresh_env())
    assert proc.returncode == EXIT_INTERRUPTED, proc.stdout + proc.stderr
    assert proc.stderr == "certify: interrupted\n", proc.stderr  # one line, nothing ignored
    assert proc.stdout == ""
    names = sorted(p.name for p in tmp_path.iterdir())
    assert not [n for n in names if n.startswith(".")], names  # no temporary file left
    if where == "commit":  # held back until every report was in place: all complete
        assert json.loads((tmp_path / "r.json").read_text())["verdict"] == "CERTIFIED"
        assert (tmp_path / "r.html").read_text().rstrip().endswith("</html>")
        assert (tmp_path / "r.xml").read_text().startswith("<?xml")
    else:  # nothing written: the earlier reports untouched
        assert (tmp_path / "r.html").read_text() == "an earlier report\n"
        assert (tmp_path / "r.json").read_text() == "an earlier report\n"
        assert not (tmp_path / "r.xml").exists()


def test_interrupt_handling_leaves_the_callers_handler_alone(capsys):
    import signal

    before = signal.getsignal(signal.SIGINT)
    assert main(["systems"]) == 0
    assert signal.getsignal(signal.SIGINT) is before
    capsys.readouterr()


# ----- scheduler, workers, closed pipes --------------------------------------------------------
@pytest.mark.parametrize("address", ["notanaddress", "tcp://", "http://host:8786",
                                     "tcp://host:99999", "tcp://host:abc", "tcp://:8786"])
@pytest.mark.slow
def test_a_malformed_scheduler_is_one_line_before_anything_connects(tmp_path, address):
    code, out, err, imported = probe("run", str(VDP), "--scheduler", address, "--json",
                                     "c.json", cwd=tmp_path)
    assert code == 2, err
    _one_error_line(err)  # no ignored Client.__del__ traceback after it
    assert "scheduler must be a Dask scheduler address" in err and address in err, err
    assert "Exception ignored" not in err and "torch" not in (imported or [])
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("address", ["inproc://elsewhere/1/2", "tls://127.0.0.1:1"])
@pytest.mark.slow
def test_a_scheduler_that_cannot_be_used_is_one_line_without_an_ignored_traceback(tmp_path,
                                                                                  address):
    """Well-formed, but refused by the client as it connects (an in-process address of
    another process; TLS without its configuration): the client that failed is closed at
    once, so nothing is printed after the one line when the interpreter exits."""
    code, out, err, _ = probe("run", str(VDP), "--scheduler", address, cwd=tmp_path)
    assert code == 2, err
    _one_error_line(err)
    assert f"--scheduler {address}: cannot connect to a Dask scheduler" in err, err
    assert "Exception ignored" not in err


@pytest.mark.slow
def test_a_malformed_scheduler_in_the_policy_file_is_refused(workdir, capsys):
    (workdir / "pyproject.toml").write_text(FAST_POLICY + 'scheduler = "host-without-port"\n')
    code, _, err = run_cli(capsys, "run", str(VDP))
    assert code == 2 and "[tool.certify] scheduler must be" in err, err
    _one_error_line(err)


def test_workers_are_capped_with_one_line(workdir, capsys):
    cap = max_local_workers()
    for value in ("100000", str(cap + 1)):
        code, _, err = run_cli(capsys, "run", str(VDP), "--workers", value, "--json", "c.json")
        assert code == 2, err
        _one_error_line(err)
        assert f"workers must be at most {cap}" in err and "--scheduler" in err, err
    assert not (workdir / "c.json").exists()
    assert VerifySettings(workers=cap).workers == cap
    with pytest.raises(SettingsError, match="at most"):
        VerifySettings(workers=cap + 1)
    # with a scheduler the local cap does not apply (the cluster decides)
    assert VerifySettings(workers=10**6, scheduler="tcp://127.0.0.1:8786").workers == 10**6


@pytest.mark.parametrize("argv", [["systems"], ["systems", "vdp"], ["completion", "bash"],
                                  ["run", "lin.ckpt", "--json", "-", "--quiet"]])
@pytest.mark.slow
def test_a_closed_stdout_is_the_readers_choice_not_a_crash(tmp_path, argv):
    """The reader went away before certify wrote (deterministic: its end is closed before
    the process starts): exit 141, as a Unix tool killed by SIGPIPE, and nothing on
    stderr."""
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    save_linear(tmp_path / "lin.ckpt")
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run([sys.executable, "-m", "certify", *argv], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=600, cwd=tmp_path,
                              env=fresh_env())
    finally:
        os.close(write_end)
    assert proc.returncode == EXIT_CLOSED_PIPE, proc.stderr
    assert proc.stderr == ""


def test_certify_systems_piped_into_head(tmp_path):
    proc = subprocess.run(["bash", "-c", "python -m certify systems | head -1; "
                                         "echo \"status ${PIPESTATUS[0]}\""],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**fresh_env(), "PATH": os.path.dirname(sys.executable)
                               + os.pathsep + os.environ.get("PATH", "")})
    lines = proc.stdout.splitlines()
    assert len(lines) == 2 and lines[0].split()[0] in ("duffing", "lorenz", "vdp"), lines
    assert lines[1] in ("status 0", f"status {EXIT_CLOSED_PIPE}"), lines  # wrote in time, or not
    assert proc.stderr == ""


# ----- errors in the words the user typed ------------------------------------------------------
@pytest.mark.parametrize("argv, words", [
    (["run", str(VDP), "--require", "foo"], "--require must be a list of check names"),
    (["run", str(VDP), "--sim-time", "-1"], "--sim-time must be a number > 0; got -1.0"),
    (["run", str(VDP), "--noise", "nan"], "--noise must be a number >= 0; got nan"),
    (["train", "vdp"], "-o/--output (see 'certify train --help')"),
])
def test_a_bad_flag_value_is_named_by_its_flag(tmp_path, monkeypatch, capsys, argv, words):
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, *argv)
    assert code == 2 and words in err and out == "", err
    _one_error_line(err)


def test_a_file_that_is_not_a_certificate_is_named(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.json").write_text("{}")
    code, _, err = run_cli(capsys, "report", "bad.json", "--html", "r.html")
    assert code == 2 and "bad.json: not a certify certificate" in err, err
    assert not (tmp_path / "r.html").exists()
