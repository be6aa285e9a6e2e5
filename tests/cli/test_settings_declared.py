"""Every setting is declared once (`certify.settings.DECLARATIONS`): the options of
`certify run`, the `[tool.certify]` keys, the reports' settings rows and the defaults of
`VerifySettings()` all come from there; retired settings and bad budgets are refused with one
line (exit 2) before any checkpoint is read."""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from pathlib import Path

import pytest

from certify.cli import commands
from certify.cli.config import FLAGS, load_settings
from certify.cli.main import main
from certify.cli.parser import build_parser
from certify.errors import SettingsError
from certify.settings import (
    DECLARATIONS,
    DECLARED,
    FIELD_NAMES,
    RETIRED,
    VerifySettings,
    flag_of,
    make_settings,
    settings_rows,
)

ROOT = Path(__file__).resolve().parents[2]
VDP = ROOT / "examples" / "vdp.ckpt"
#: the options of `certify run` that are not settings
NOT_SETTINGS = {"-h", "--help", "--debug", "--system", "--lam", "--metric", "--activation",
                "--structure", "--html", "--pdf", "--json", "--junit", "--trajectories",
                "--config", "--no-config", "--quiet", "-q"}


def _run_parser() -> argparse.ArgumentParser:
    parser = build_parser(with_train=False)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["run"]


def test_every_option_of_run_is_a_declared_setting_or_named_here():
    run = _run_parser()
    options = {opt: a for a in run._actions for opt in a.option_strings}
    declared = {d.flag: d for d in DECLARATIONS if d.flag}
    retired = {flag_of(old) for old in RETIRED}
    assert set(options) == NOT_SETTINGS | set(declared) | retired
    for flag, decl in declared.items():
        action = options[flag]
        assert action.dest == decl.name and action.default is None  # [tool.certify] applies
        assert action.help.startswith(decl.help)
    for flag in retired:
        assert options[flag].help == argparse.SUPPRESS


def test_config_keys_and_flag_names_are_the_declarations(tmp_path):
    assert FLAGS == {d.name: d.flag for d in DECLARATIONS if d.flag}
    assert FIELD_NAMES == tuple(f.name for f in dataclasses.fields(VerifySettings))
    # every declared key is read from [tool.certify] (here: each at its default)
    lines = []
    for d in DECLARATIONS:
        if d.default is None:
            continue
        value = d.default
        text = (repr(value).lower() if isinstance(value, bool) else
                "[" + ", ".join(f'"{v}"' for v in value) + "]" if isinstance(value, tuple)
                else f'"{value}"' if isinstance(value, str) else repr(value))
        lines.append(f"{d.name} = {text}")
    path = tmp_path / "pyproject.toml"
    path.write_text("[tool.certify]\n" + "\n".join(lines) + "\n")
    settings, source = load_settings({}, path)
    assert settings == VerifySettings() and source == str(path)
    path.write_text("[tool.certify]\nmax_boxs = 3\n")
    with pytest.raises(SettingsError, match="unknown key.*max_boxs.*known: " + FIELD_NAMES[0]):
        load_settings({}, path)


def test_the_declared_defaults_are_the_settings_defaults():
    defaults = VerifySettings()
    assert {d.name: d.default for d in DECLARATIONS} == dataclasses.asdict(defaults)
    assert make_settings({}) == defaults


def test_every_settings_row_is_a_declaration_with_its_unit():
    values = dataclasses.asdict(VerifySettings(max_seconds=30.0))
    rows = settings_rows(values)
    assert [label for label, _ in rows] == [d.label for d in DECLARATIONS]
    shown = dict(rows)
    assert shown[DECLARED["max_boxes"].label] == "2,000,000 boxes"
    assert shown[DECLARED["max_seconds"].label] == "30 s"
    assert shown[DECLARED["sim_time"].label] == "automatic"
    assert shown[DECLARED["noise"].label] == "0.15"
    # an older certificate's retired setting keeps a row of its own, by its old label
    old = settings_rows({"proof_seconds": 60.0, "max_boxes": 2_000_000})
    assert old == [("MPDI proof budget", "2,000,000 boxes"), ("MPDI proof time budget", "60 s")]


def test_one_name_for_the_noise_bound():
    run = _run_parser()
    assert "--noise" in {o for a in run._actions for o in a.option_strings}
    assert "noise" in FIELD_NAMES and not any("vbar" in n for n in FIELD_NAMES)
    assert all("vbar" not in d.label and "vbar" not in (d.flag or "") for d in DECLARATIONS)


def _refused(capsys, *argv: str) -> str:
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert err.startswith("certify: error: ") and err.count("\n") == 1 and out == "", err
    return err


@pytest.fixture
def no_loading(monkeypatch, tmp_path):
    """Any checkpoint read fails the test: usage errors come before it."""
    from certify.model import checkpoint

    def load(*a, **k):
        raise AssertionError("the checkpoint was read before the usage error")

    monkeypatch.setattr(checkpoint, "load", load)
    monkeypatch.chdir(tmp_path)


@pytest.mark.parametrize("old", sorted(RETIRED))
def test_a_retired_option_names_its_replacement(capsys, no_loading, old):
    err = _refused(capsys, "run", str(VDP), flag_of(old), "30")
    assert f"{flag_of(old)} was replaced by {flag_of(RETIRED[old])}" in err
    assert "--max-seconds" in err
    # given beside its replacement it is refused the same way
    err = _refused(capsys, "run", str(VDP), flag_of(RETIRED[old]), "1000", flag_of(old), "30")
    assert f"{flag_of(old)} was replaced by" in err


@pytest.mark.parametrize("old", sorted(RETIRED))
def test_a_retired_config_key_names_its_replacement(capsys, no_loading, tmp_path, old):
    (tmp_path / "pyproject.toml").write_text(f"[tool.certify]\n{RETIRED[old]} = 1000\n"
                                             f"{old} = 60\n")
    err = _refused(capsys, "run", str(VDP))
    assert f"[tool.certify] in {tmp_path / 'pyproject.toml'}: {old} was replaced by " \
           f"{RETIRED[old]}" in err
    with pytest.raises(SettingsError, match=f"{old} was replaced by {RETIRED[old]}"):
        make_settings({old: 60})


@pytest.mark.parametrize("argv, words", [
    (["--max-seconds", "0"], "--max-seconds must be a number > 0; got 0.0"),
    (["--max-seconds", "-5"], "--max-seconds must be a number > 0; got -5.0"),
    (["--max-seconds", "inf"], "--max-seconds must be a number > 0; got inf"),
    (["--max-boxes", "1e30"], "argument --max-boxes: at most 1e+12; got '1e30'"),
    (["--max-boxes", "2.5"], "argument --max-boxes: not an integer: '2.5'"),
    (["--rate-boxes", "many"], "argument --rate-boxes: not an integer: 'many'"),
    (["--dissipation-boxes", "0"], "--dissipation-boxes must be an int >= 1; got 0"),
    (["--lipschitz-boxes", "-3"], "--lipschitz-boxes must be an int >= 1; got -3"),
    (["--residual-boxes", "2000000000000"], "--residual-boxes must be an int <= "),
    (["--lam", "-1"], "--lam must be a finite number > 0"),
    (["--metric", "[[1, 2], [3, 4]]"], "--metric must be symmetric"),
    (["--activation", "tanh"], "--activation: only for a model from elsewhere"),
])
def test_bad_budgets_and_values_are_refused_before_loading(capsys, no_loading, argv, words):
    assert words in _refused(capsys, "run", str(VDP), "--no-config", *argv)


def test_a_box_budget_written_with_an_exponent_is_read_exactly():
    run = _run_parser()
    args = run.parse_args([str(VDP), "--max-boxes", "2e6", "--rate-boxes", "1_000"])
    assert (args.max_boxes, args.rate_boxes) == (2_000_000, 1000)


def test_config_budgets_are_checked_like_options(tmp_path):
    path = tmp_path / "pyproject.toml"
    for text, words in (("max_boxes = 1e30", "max_boxes must be an int >= 1; got 1e+30"),
                        ("max_boxes = 10000000000000", "max_boxes must be an int <= "),
                        ("max_seconds = 0", "max_seconds must be a number > 0; got 0.0"),
                        ("rate_boxes = 2.5", "rate_boxes must be an int >= 1; got 2.5")):
        path.write_text(f"[tool.certify]\n{text}\n")
        with pytest.raises(SettingsError, match=words.replace("+", r"\+")):
            load_settings({}, path)


def test_repeated_skip_and_require_accumulate():
    run = _run_parser()
    args = run.parse_args([str(VDP), "--skip", "simulation", "--skip", "rate,bounds",
                           "--require", "residual", "--require", "mpdi"])
    settings, _ = load_settings(commands._flag_settings(args), use_pyproject=False)
    assert settings.skip == ("simulation", "rate", "bounds")
    assert settings.required == ("residual", "mpdi")


def test_warnings_go_to_the_debug_log_not_the_output(capsys, caplog, monkeypatch):
    import logging

    def noisy(args):
        warnings.warn("overflow encountered in multiply", RuntimeWarning, stacklevel=1)
        return 0

    monkeypatch.setattr(commands, "cmd_systems", noisy)
    with caplog.at_level(logging.DEBUG, logger="certify"):
        assert main(["systems"]) == 0
    out, err = capsys.readouterr()
    assert "overflow" not in out + err
    assert "RuntimeWarning: overflow encountered in multiply" in caplog.text
