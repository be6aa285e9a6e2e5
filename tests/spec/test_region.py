"""The spec's [invariance] region: well-formed regions read, bad ones refused with one line
(in the reader and on the command line: exit 2)."""

from __future__ import annotations

import numpy as np
import pytest

from certify.errors import SpecError
from certify.spec.system import System

from ..cli_helpers import run_cli

BASE = """
name = "pend"
states = ["th", "om"]
outputs = ["y"]
f = ["om", "-sin(th) - 0.2*om"]
h = ["th"]

[box]
X = [[-1, 1], [-2, 2]]
Y = [[-1, 1]]
"""


def spec(region: str) -> str:
    return BASE + "\n[invariance]\n" + region + "\n"


def test_a_polygon_reads_counter_clockwise():
    clockwise = "polygon = [[0.5, 0.0], [0.0, -0.5], [-0.5, 0.0], [0.0, 0.5]]"
    s = System.from_text(spec(clockwise), origin="spec p.toml")
    v = s.invariance.vertices
    area = 0.5 * np.sum(v[:, 0] * np.roll(v, -1, 0)[:, 1] - np.roll(v, -1, 0)[:, 0] * v[:, 1])
    assert s.invariance.kind == "polygon" and area > 0 and len(v) == 4


def test_no_table_no_region():
    assert System.from_text(BASE, origin="spec p.toml").invariance is None


@pytest.mark.parametrize("region, words", [
    ("polygon = [[0.5, 0.0], [0.0, 0.5]]", "is degenerate: it has 2 vertices"),
    ("polygon = [[0.5, 0.0], [0.0, 0.5], [0.0, 0.5], [-0.5, 0.0]]",
     "is degenerate: vertices 1 and 2 coincide"),
    ("polygon = [[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]]", "is degenerate: it encloses no area"),
    ("polygon = [[-0.5, -0.5], [0.5, 0.6], [0.5, -0.5], [-0.5, 0.2]]",
     "is not a simple polygon"),
    ("polygon = [[0.0, 0.0], [0.8, 0.0], [0.4, 0.0], [0.4, 0.5]]", "fold back"),
    ("polygon = [[0.5, 0.0], [0.0, 0.5], [-1.5, 0.0], [0.0, -0.5]]",
     "is not inside X: vertex 2 = (-1.5, 0) lies outside X"),
    ("polygon = [[0.5, 0.0], [0.0, 0.5], [-0.5, nan]]", "non-finite"),
    ("polygon = 3", "must be a list of [x1, x2] vertices"),
    ("box = [[-0.5, 0.5], [-2.5, 0.5]]", "is not inside X: row 1 [-2.5, 0.5]"),
    ("box = [[0.5, -0.5], [-1, 1]]", "row 0 is empty or inverted"),
    ("box = [[-0.5, 0.5]]", "must have 2 rows"),
    ('V = "th**2 + om**2"\nlevel = 1.5', "is not inside X: it reaches the boundary of X"),
    ('V = "th**2 + om**2"\nlevel = -1', "is empty at every point tried"),
    ('V = "th**2 + om**2"', "V needs a level"),
    ('V = "th**2 + zz"\nlevel = 0.5', "zz"),
    ('V = "log(th)"\nlevel = 0.5', "log"),
    ("level = 0.5", "needs exactly one of polygon, box or V"),
    ('box = [[-0.5, 0.5], [-0.5, 0.5]]\nV = "th**2"\nlevel = 0.1',
     "needs exactly one of polygon, box or V"),
    ('V = "th**2 + om**2"\nlevel = "big"', "level must be a finite number"),
])
def test_a_bad_region_is_refused_with_one_line(region, words):
    with pytest.raises(SpecError) as info:
        System.from_text(spec(region), origin="spec p.toml")
    text = str(info.value)
    assert words in text and "\n" not in text and text.startswith("spec p.toml")


def test_a_polygon_needs_two_states():
    three = BASE.replace('["th", "om"]', '["th", "om", "z"]').replace(
        '"-sin(th) - 0.2*om"]', '"-sin(th) - 0.2*om", "-z"]').replace(
        "X = [[-1, 1], [-2, 2]]", "X = [[-1, 1], [-2, 2], [-1, 1]]")
    with pytest.raises(SpecError, match="polygon needs n = 2 states; this system has 3"):
        System.from_text(three + "[invariance]\npolygon = [[0, 0], [0.1, 0], [0, 0.1]]\n",
                         origin="spec p.toml")


@pytest.mark.parametrize("region, words", [
    ("polygon = [[0.5, 0.0], [0.0, 0.5], [-1.5, 0.0], [0.0, -0.5]]", "is not inside X"),
    ("polygon = [[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]]", "is degenerate"),
])
def test_the_command_line_refuses_a_bad_region_with_exit_2(tmp_path, capsys, region, words):
    path = tmp_path / "bad.toml"
    path.write_text(spec(region))
    code, out, err = run_cli(capsys, "check", str(path))
    assert code == 2, (out, err)
    assert words in err and err.startswith("certify: error: ") and err.count("\n") == 1
