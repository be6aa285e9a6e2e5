"""The tests mirror the packages: every test file lives in the folder of the package it tests
(one per stage package of `certify`, plus `training`, `reports`, `end_to_end` for whole runs
across packages and `project` for project-wide rules); only the shared helpers (conftest,
cli_helpers, planted, fixtures_certificates, mp_reference, soak) and `data/` sit at the top."""

from __future__ import annotations

from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
ROOT = TESTS.parent
#: folders beside the mirrors of certify's subpackages
EXTRA = {"training", "reports", "end_to_end", "project"}
NOT_TESTS = {"data", "__pycache__"}


def _folders() -> set[str]:
    return {d.name for d in TESTS.iterdir()
            if d.is_dir() and d.name not in NOT_TESTS and not d.name.startswith(".")}


def test_no_test_file_at_the_top_of_tests():
    loose = sorted(p.name for p in TESTS.glob("test_*.py"))
    assert not loose, ("test files at the top of tests/; move each (git mv) into the folder "
                       f"of the package it tests, one of {sorted(_folders())}: {loose}")


def test_the_folders_mirror_the_packages():
    packages = {d.name for d in (ROOT / "certify").iterdir() if (d / "__init__.py").exists()}
    assert _folders() == packages | EXTRA
    unimportable = sorted(f for f in _folders() if not (TESTS / f / "__init__.py").exists())
    assert not unimportable, f"test folders without __init__.py: {unimportable}"
