"""Command-line conventions through the real CLI: output paths checked before any work,
`--json -`, `python -m certify`, `--version` from metadata, help that lists the checks,
shell completion, light start-up, and `certify check` exit codes."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from importlib import metadata

import pytest

from certify.cli.main import main
from certify.settings import CHECK_NAMES

from ..cli_helpers import FAST_POLICY, ROOT, probe, run_cli, save_linear
from ..conftest import LINEAR_SPEC

EXAMPLE = str(ROOT / "examples" / "vdp_certified.ckpt")


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    return tmp_path


@pytest.mark.parametrize("argv, words", [
    (["run", EXAMPLE, "--html", "/proc/x/r.html"], "--html /proc/x/r.html: directory /proc/x "
                                                   "does not exist"),
    (["run", EXAMPLE, "--pdf", "/proc/r.pdf"], "--pdf /proc/r.pdf: cannot create a file in /proc"),
    (["run", EXAMPLE, "--json", "{tmp}"], "is a directory, not a file"),
    (["run", EXAMPLE, "--junit", "-"], "--junit -: writing to stdout is supported only for --json"),
    (["run", EXAMPLE, "--html", "{tmp}/a", "--pdf", "{tmp}/a"], "the same file is already the "
                                                                "--html output"),
    (["report", "{tmp}/none.json", "--json", "/proc/x/c.json"], "--json /proc/x/c.json"),
    (["check", "vdp", "--json", "/proc/x/c.json"], "--json /proc/x/c.json: directory /proc/x"),
    (["train", "vdp", "-o", "/proc/x/m.ckpt"], "-o /proc/x/m.ckpt: directory /proc/x"),
])
def test_output_paths_are_checked_before_any_work(tmp_path, argv, words):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, out, err, imported = probe(*argv)
    assert code == 2, err
    assert err.startswith("certify: error: ") and err.count("\n") == 1, err
    assert words in err, err
    assert out == "" and "Traceback" not in err
    # refused before the checkpoint or the spec was even read: nothing heavy was imported
    # (train's options come from the training code, which imports torch to list them)
    assert imported == [] or argv[0] == "train", imported
    assert not (tmp_path / "a").exists()


@pytest.mark.slow
def test_json_to_stdout_and_everything_else_to_stderr(workdir, capsys):
    path = save_linear(workdir / "lin.ckpt")
    code, out, err = run_cli(capsys, "run", path, "--json", "-", "--html", "r.html")
    assert code == 0, err
    cert = json.loads(out)  # stdout is exactly the certificate
    assert cert["verdict"] == "CERTIFIED" and cert["schema"] == "certify-certificate"
    assert "CERTIFIED: all required checks proved" in err  # the summary went to stderr
    assert (workdir / "r.html").exists() and not (workdir / "-").exists()
    code, out, err = run_cli(capsys, "report", "r.html", "--json", "-")
    assert code == 2 and out == ""


def test_python_m_certify_and_version_from_metadata():
    proc = subprocess.run([sys.executable, "-m", "certify", "--version"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0
    assert proc.stdout == f"certify {metadata.version('certify')}\n"


def test_help_lists_check_names_exit_codes_and_examples(capsys):
    assert main(["--help"]) == 0
    top = capsys.readouterr().out
    assert "examples:" in top and "certify run vdp.ckpt --json -" in top
    assert "4 internal error" in top and "completion" in top
    assert main(["run", "--help"]) == 0
    text = re.sub(r"\s+", " ", capsys.readouterr().out)
    assert f"from: {', '.join(CHECK_NAMES)}" in text  # for --require and --skip
    assert "--debug" in text and "3 inconclusive" in text


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["systems"], ["run", "--help"]])
def test_light_commands_do_not_import_heavy_libraries(argv):
    code, out, _, imported = probe(*argv)
    assert code == 0 and imported == [], imported
    if argv == ["systems"]:
        assert re.search(r"^vdp +n=2 p=1 ", out, re.M) and "duffing" in out


@pytest.mark.skipif(shutil.which("bash") is None, reason="bash not installed")
def test_bash_completion_completes_commands_and_check_lists(tmp_path, capsys):
    def generate(shell: str) -> str:
        assert main(["completion", shell]) == 0
        return capsys.readouterr().out

    script = tmp_path / "certify.bash"
    script.write_text(generate("bash"))

    def complete(*words: str) -> list[str]:
        line = " ".join(shlex.quote(w) for w in words)
        cmd = (f'source {script}; COMP_WORDS=({line}); COMP_CWORD={len(words) - 1}; '
               'COMPREPLY=(); _certify; printf "%s\\n" "${COMPREPLY[@]}"')
        out = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, check=True)
        return out.stdout.split()

    assert "run" in complete("certify", "r") and "report" in complete("certify", "r")
    assert complete("certify", "run", "x.ckpt", "--req") == ["--require"]
    assert complete("certify", "run", "x.ckpt", "--require", "mpdi,ra") == ["mpdi,rate"]
    # the MPDI is the certificate: --skip never offers it (it would be refused)
    assert complete("certify", "run", "x.ckpt", "--skip", "") == \
        [c for c in CHECK_NAMES if c != "mpdi"]
    assert complete("certify", "run", "x.ckpt", "--skip", "rate,m") == ["rate,metric_bound"]
    assert complete("certify", "run", "x.ckpt", "--skip", "rate,mp") == []
    assert complete("certify", "completion", "") == ["bash", "zsh", "fish"]
    assert complete("certify", "train", "vdp", "--preset", "") == ["paper", "tiny", "certified",
                                                                    "bound"]
    assert "bashcompinit" in generate("zsh")
    fish = generate("fish")
    assert ("__fish_seen_subcommand_from run' -l require -x -a "
            f"'(__certify_checks {' '.join(CHECK_NAMES)})'") in fish


@pytest.mark.slow
def test_check_exit_codes_follow_the_spec_as_given(tmp_path, capsys):
    spec = tmp_path / "linear.toml"
    spec.write_text(LINEAR_SPEC)
    code, out, _ = run_cli(capsys, "check", str(spec))
    assert code == 0 and "passes the pre-flight (exit 0)" in out
    # vdp with P = I fails; the metric the SDP finds is printed as the fix, and it works
    code, out, _ = run_cli(capsys, "check", "vdp", "--json", str(tmp_path / "c.json"))
    assert code == 1 and "fails the pre-flight (exit 1)" in out
    fix = next(line for line in out.splitlines() if line.strip().startswith("fix: certify check"))
    record = json.loads((tmp_path / "c.json").read_text())
    assert record["necessary"]["status"] == "VIOLATED" and record["metric"]["status"] == "PROVED"
    argv = shlex.split(fix.split("fix: certify ", 1)[1])
    code, out, _ = run_cli(capsys, *argv, "--no-synthesis")
    assert code == 0, out
    assert out.rstrip().endswith("the spec with --lam and --metric passes the pre-flight "
                                 "(exit 0)"), out  # what passed is the spec as changed
    code, out, _ = run_cli(capsys, "check", "vdp", "--no-synthesis")
    assert code == 1 and out.rstrip().endswith("the spec as given fails the pre-flight (exit 1)")


@pytest.mark.parametrize("argv, words", [
    (["check", "vdp", "--lam", "inf"], "--lam must be a finite number > 0; got inf"),
    (["check", "vdp", "--lam", "nan"], "--lam must be a finite number > 0; got nan"),
    (["check", "vdp", "--lam", "1e308"], "--lam must be at most 1e+12"),
    (["train", "vdp", "--lam", "1e308", "-o", "{tmp}/m.ckpt"], "lam (--lam) must be a finite "
                                                              "number in (0, 1e+12]"),
])
def test_absurd_rates_are_bad_input(tmp_path, capsys, argv, words):
    """An infinite, NaN or overflowing rate is exit 2 with one line (it was exit 4: 2 lam P
    overflowed inside the metric SDP), and nothing is written."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code, out, err = run_cli(capsys, *argv)
    assert code == 2, err
    assert err.startswith("certify: error: ") and err.count("\n") == 1, err
    assert words in err, err
    assert list(tmp_path.iterdir()) == []
