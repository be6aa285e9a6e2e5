"""docs/spec-format.md documents exactly the keys the spec reader accepts: every key in its
tables is accepted (a spec using all of them reads), every key the reader knows is in the
tables, and a key that is not there is refused naming it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from certify.errors import SpecError
from certify.spec.system import SPEC_KEYS, System, tomllib

DOC = Path(__file__).resolve().parents[2] / "docs" / "spec-format.md"
#: a section of the doc: '## Top level' or '## `[table]`'
HEADING = re.compile(r"^## (?:(Top level)|`\[([\w.]+)\]`)\s*$")
#: a row of a key table: '| `key` | ...'
ROW = re.compile(r"^\|\s*`(\w+)`\s*\|")


def documented_keys() -> dict[str, set[str]]:
    """table ('' for the top level) -> the keys of its table in the doc."""
    out: dict[str, set[str]] = {}
    table: str | None = None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            m = HEADING.match(line)
            table = None if m is None else ("" if m.group(1) else m.group(2))
            if table is not None:
                out.setdefault(table, set())
        elif table is not None and (m := ROW.match(line)):
            out[table].add(m.group(1))
    return out


def test_the_doc_lists_every_key_the_reader_knows_and_no_other():
    doc = documented_keys()
    assert set(doc) == set(SPEC_KEYS), "a table is documented that the reader does not know"
    for table, keys in SPEC_KEYS.items():
        assert doc[table] == set(keys), f"[{table or 'top level'}]"


def _full_spec() -> str:
    """A spec that sets every documented key."""
    return """
name = "full"
description = "every key"
states = ["a", "b"]
outputs = ["y"]
f = ["b", "-sin(a) - 0.2*b"]
h = ["a"]

[box]
X = [[-1, 1], [-2, 2]]
Y = [[-1.5, 1.5]]

[design]
lam = 0.5
P = [[3, -1], [-1, 1]]

[design.state_metric]
kind = "polynomial"
format = 1
exponents = [[0, 0], [1, 1]]
coefficients = [[[3, -1], [-1, 1]], [[0.1, 0], [0, 0.1]]]

[training.paper]
mu1 = 1e-3
mu2 = 1.0
rho = [1.0, 0.1]

[simulation]
x0 = [0.5, 0.0]
xhat0 = [0.0, 0.0]
t_final = 5.0

[invariance]
V = "a**2 + b**2"
level = 0.5
"""

#: the other forms of [invariance] (its keys exclude each other: one region per spec)
REGIONS = ('polygon = [[0.5, 0.0], [0.0, 0.5], [-0.5, 0.0], [0.0, -0.5]]',
           'box = [[-0.5, 0.5], [-0.5, 0.5]]')


def _with_region(text: str, region: str) -> str:
    return text.replace('V = "a**2 + b**2"\nlevel = 0.5', region)


def _keys_of(data: dict, prefix: str = "") -> dict[str, set[str]]:
    out = {prefix: set(data)}
    for k, v in data.items():
        if isinstance(v, dict):
            out.update(_keys_of(v, f"{prefix}.{k}" if prefix else k))
    return out


def test_a_spec_with_every_documented_key_reads():
    texts = [_full_spec()] + [_with_region(_full_spec(), r) for r in REGIONS]
    keys: dict[str, set[str]] = {}
    for text in texts:
        for table, found in _keys_of(tomllib.loads(text)).items():
            keys.setdefault(table, set()).update(found)
    assert keys == documented_keys()
    systems = [System.from_text(t, origin="spec full.toml") for t in texts]
    system = systems[0]
    assert system.lam == 0.5 and system.training["paper"]["mu1"] == 1e-3
    assert system.simulation["x0"] == [0.5, 0.0]
    assert [s.invariance.kind for s in systems] == ["sublevel", "polygon", "box"]


@pytest.mark.parametrize("table, key", [("", "lamb"), ("box", "Z"), ("design", "lamda"),
                                        ("training.paper", "mu3"), ("simulation", "x1"),
                                        ("invariance", "levels")])
def test_a_key_that_is_not_documented_is_refused_by_name(table, key):
    text = _full_spec()
    header = f"[{table}]\n" if table else None
    if header is None:  # top level: before the first table
        text = f"{key} = 1\n" + text
    elif header in text:
        text = text.replace(header, f"{header}{key} = 1\n")
    else:
        text += f"\n{header}{key} = 1\n"
    with pytest.raises(SpecError, match=f"unknown key '{key}'"):
        System.from_text(text, origin="spec typo.toml")


def test_a_table_that_is_not_a_table_is_refused():
    full = _full_spec()
    text = full[:full.index("[design]")] + full[full.index("[training.paper]"):]
    with pytest.raises(SpecError, match=r"\[design\] must be a table"):
        System.from_text("design = 3\n" + text, origin="spec bad.toml")
