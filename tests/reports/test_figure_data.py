"""The certificate's figure arrays at figure size: the JSON stays small and re-renders the
same reports, and nothing a figure must show is lost on the way down (the worst grid value,
every cell > 0 of a map, every counterexample, a spike or a breach of a simulated run, a
violated prover box)."""

from __future__ import annotations

import dataclasses
import json
import math

import matplotlib
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.certificate import SCHEMA_VERSION, Certificate, format_json  # noqa: E402
from certify.checks.simulation import MAX_SAMPLES, keep_samples  # noqa: E402
from certify.figuredata import (  # noqa: E402
    MAP_POINTS,
    FigureData,
    GridMap,
    ProofBoxes,
    downsample_max,
    round_sig,
)
from certify.results import Counterexample  # noqa: E402
from reports import figures as figmod  # noqa: E402
from reports.figures import drawn  # noqa: E402
from reports.render import render_reports  # noqa: E402

from .. import fixtures_certificates as F  # noqa: E402
from ..cli_helpers import FAST_POLICY, run_cli, save_linear  # noqa: E402

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


# ----------------------------------------------------------------------------- numbers

@given(st.floats(allow_nan=True, allow_infinity=True), st.integers(1, 9))
def test_round_sig_keeps_sign_zero_and_non_finite(v: float, digits: int) -> None:
    r = round_sig(v, digits)
    if math.isnan(v):
        assert math.isnan(r)
        return
    assert (r > 0) == (v > 0) and (r < 0) == (v < 0) and (r == 0) == (v == 0)
    if math.isfinite(v) and v != 0:
        assert abs(r - v) <= 0.5 * 10 ** (1 - digits) * abs(v) * (1 + 1e-9)
    assert round_sig(r, digits) == r or (math.isnan(r) and math.isnan(round_sig(r, digits)))


json_data = st.recursive(
    st.none() | st.booleans() | finite | st.text(max_size=12) | st.integers(-10**9, 10**9),
    lambda inner: st.lists(inner, max_size=40) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=6),
    max_leaves=300)


@settings(max_examples=60, deadline=None)
@given(json_data)
@pytest.mark.slow
def test_format_json_reads_back_and_keeps_lines_short(data) -> None:
    text = format_json(data)
    assert json.loads(text) == data
    if isinstance(data, list) and all(isinstance(v, float) for v in data):
        assert all(len(line) <= 100 + 30 for line in text.splitlines())


# ----------------------------------------------------------------------------- maps

def _coarse_index(fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
    """The coarse point whose cell holds each fine point (the nearest one)."""
    return np.argmin(np.abs(fine[:, None] - coarse[None, :]), axis=1)


def _check_map(v: np.ndarray) -> None:
    ny, nx = v.shape
    x, y = np.linspace(-2.0, 2.0, nx), np.linspace(-3.0, 3.0, ny)
    cx, cy, cv = (np.asarray(a, dtype=float) for a in downsample_max(x.tolist(), y.tolist(),
                                                                      v.tolist()))
    assert len(cx) == min(nx, MAP_POINTS) and len(cy) == min(ny, MAP_POINTS)
    assert (cx[0], cx[-1], cy[0], cy[-1]) == (x[0], x[-1], y[0], y[-1])  # the same box
    fin = np.isfinite(v)
    if fin.any():  # the worst grid value survives exactly
        assert np.nanmax(cv) == np.max(v[fin])
    ix, iy = _coarse_index(x, cx), _coarse_index(y, cy)
    for j, i in zip(*np.nonzero(fin)):  # every fine value is under its coarse cell's value
        assert cv[iy[j], ix[i]] >= v[j, i]
    assert np.isnan(cv).sum() <= np.isnan(v).sum()  # NaN only where every fine cell is NaN


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 90), st.integers(1, 90), st.integers(0, 2**32 - 1),
       st.floats(0.0, 0.9))
def test_downsampled_map_keeps_the_worst_value_and_every_positive_cell(nx, ny, seed, nan):
    rng = np.random.default_rng(seed)
    v = rng.normal(-1.0, 1.0, (ny, nx))
    v[rng.random((ny, nx)) < nan] = np.nan
    _check_map(v)


def test_a_single_positive_cell_between_coarse_points_stays_positive_on_the_figure():
    """A 61 x 61 map below zero but for one cell at an odd index (plain decimation by two
    would drop it): after compaction the map still has a cell > 0, the figure draws two
    signs, and the worst value is exact."""
    X = [[-2.0, 2.0], [-3.0, 3.0]]
    x, y = np.linspace(*X[0], 61), np.linspace(*X[1], 61)
    v = -1.0 - 0.1 * np.add.outer(y ** 2, x ** 2)
    v[31, 17] = 3e-7  # tiny and positive: a violation on the map
    grid = GridMap(x=x.tolist(), y=y.tolist(), values=v.tolist(), axes=["x1", "x2"])
    small = grid.compact()
    cv = np.asarray(small.values)
    assert cv.shape == (MAP_POINTS, MAP_POINTS)
    assert cv.max() == 3e-7 and (cv > 0).sum() >= 1
    cert = F.violated_vdp_certificate()
    cert.figures = FigureData(mpdi_map=grid).compact()
    again = Certificate.from_dict(json.loads(cert.to_json()))
    assert again.figures.mpdi_map == cert.figures.mpdi_map
    with matplotlib.rc_context(figmod.STYLE):
        d = drawn(figmod.fig_mpdi_map(again))
    assert "two signs" in d and d["range"][1] == 3e-7


@pytest.mark.slow
def test_every_counterexample_is_drawn_after_the_round_trip() -> None:
    cert = F.violated_vdp_certificate()
    X = cert.system["X"]
    rng = np.random.default_rng(3)
    cex = [Counterexample(xhat=[float(rng.uniform(*X[0])), float(rng.uniform(*X[1]))],
                          y=[0.0], value=1.0 + k, sound_bound=0.5 + k) for k in range(40)]
    cert.checks["mpdi"] = dataclasses.replace(cert.checks["mpdi"], counterexamples=cex,
                                              worst=cex[-1])
    again = Certificate.from_dict(json.loads(cert.to_json()))
    assert again.checks["mpdi"].counterexamples == cex  # exact: never thinned or rounded
    with matplotlib.rc_context(figmod.STYLE):
        fig = figmod.fig_mpdi_map(again)
    assert drawn(fig)["counterexamples"] == 40
    offsets = np.concatenate([c.get_offsets() for c in fig.axes[0].collections
                              if type(c).__name__ == "PathCollection"])
    for c in cex:
        assert np.isclose(offsets, c.xhat[:2]).all(axis=1).any()


def test_older_certificates_are_read_and_brought_to_figure_size() -> None:
    cert = F.inconclusive_certificate()
    data = json.loads(cert.to_json())
    fine = F._grid_map(cert.system["X"], lambda a, b: a * b - 0.5, nx=61, ny=61)
    data["figures"]["mpdi_map"] = fine
    data["schema_version"] = 2
    old = Certificate.from_dict(data)
    assert old.schema_version == SCHEMA_VERSION
    m = old.figures.mpdi_map
    assert len(m.x) == len(m.y) == MAP_POINTS
    assert max(map(max, m.values)) == pytest.approx(max(map(max, fine["values"])), rel=1e-3)


# ----------------------------------------------------------------------------- prover boxes

def test_coinciding_boxes_keep_the_worst_status_and_the_leaf_counts() -> None:
    lo = [[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.5], [0.5, 0.0, 1.0]]
    hi = [[0.5, 0.5, 0.0], [0.5, 0.5, 0.5], [1.0, 0.5, 1.0], [0.5, 0.5, 1.0], [1.0, 0.5, 2.0]]
    status = ["proved", "violated", "proved", "unknown", "unknown"]
    boxes = ProofBoxes(lo=lo, hi=hi, status=status, axes=["x1", "x2"]).compact()
    # one box per projection, the worst status, in drawing order (violated last, on top)
    assert boxes.lo == [[0.5, 0.0], [0.0, 0.0]] and boxes.hi == [[1.0, 0.5], [0.5, 0.5]]
    assert boxes.status == ["unknown", "violated"]
    assert boxes.counts() == {"proved": 2, "violated": 1, "unknown": 2}
    assert boxes.compact() == boxes  # idempotent
    cert = F.certified_certificate()
    cert.figures = FigureData(proof_boxes=boxes)
    with matplotlib.rc_context(figmod.STYLE):
        fig = figmod.fig_prover(cert)
    assert drawn(fig)["boxes"] == {"proved": 2, "violated": 1, "unknown": 2}
    assert fig.axes[0].get_title() == "Prover's leaf boxes (5)"


# ----------------------------------------------------------------------------- simulation

@settings(max_examples=60, deadline=None)
@given(st.integers(2, 6000), st.data())
def test_thinning_keeps_spikes_the_worst_step_and_the_exit(T: int, data) -> None:
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    error = np.exp(rng.normal(-2.0, 0.3, T))
    spike = data.draw(st.integers(0, T - 1))
    error[spike] = 50.0  # one step: a breach between two evenly spaced samples
    dip = data.draw(st.integers(0, T - 1))
    if dip != spike:
        error[dip] = 1e-9
    worst = data.draw(st.integers(0, T - 1))
    exit_index = data.draw(st.integers(0, T))
    keep = keep_samples(error, exit_index=exit_index, worst_index=worst)
    assert len(keep) <= MAX_SAMPLES and np.all(np.diff(keep) > 0)
    assert keep[0] == 0 and keep[-1] == T - 1
    must = {spike, worst, dip} | ({exit_index, max(exit_index - 1, 0)} if exit_index < T
                                  else set())
    assert must <= set(keep.tolist())
    assert {int(np.argmax(error)), int(np.argmin(error))} <= set(keep.tolist())


def test_thinning_keeps_the_first_non_finite_step() -> None:
    error = np.linspace(1.0, 2.0, 5000)
    error[3001:] = np.nan
    keep = keep_samples(error, exit_index=3001)
    assert 3001 in keep.tolist() and len(keep) <= MAX_SAMPLES


# ----------------------------------------------------------------------------- the whole run

@pytest.mark.slow
def test_small_run_writes_a_small_json_that_re_renders_the_same_reports(tmp_path, monkeypatch,
                                                                        capsys) -> None:
    """`certify run` of a small problem: the JSON is small, has no states unless asked, and
    `certify report` re-renders the run's own HTML from it, byte for byte."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pyproject.toml").write_text(FAST_POLICY)
    path = save_linear(tmp_path / "lin.ckpt")
    code, out, err = run_cli(capsys, "run", path, "--json", "c.json", "--html", "a.html",
                             "--quiet")
    assert code == 0, (out, err)
    text = (tmp_path / "c.json").read_text()
    assert len(text.encode()) < 80_000 and text.count("\n") < 2000
    cert = json.loads(text)
    assert cert["schema_version"] == SCHEMA_VERSION
    runs = cert["checks"]["simulation"]["runs"]
    assert runs and all(run["x"] == [] and run["xhat"] == [] for run in runs)
    assert all(0 < len(run["t"]) <= MAX_SAMPLES for run in runs)
    maps = [m for m in cert["figures"].values() if isinstance(m, dict) and "values" in m]
    assert maps and all(len(m["x"]) <= MAP_POINTS for m in maps)
    code, _, err = run_cli(capsys, "report", "c.json", "--html", "b.html", "--pdf", "b.pdf",
                           "--quiet")
    assert code == 0, err
    assert (tmp_path / "b.html").read_text() == (tmp_path / "a.html").read_text()
    assert (tmp_path / "b.pdf").read_bytes()[:5] == b"%PDF-"
    # the trajectories, asked for but not stored: said, and the rest is drawn
    code, _, err = run_cli(capsys, "report", "c.json", "--html", "t.html", "--trajectories")
    assert "holds no simulated states" in err
    assert code == 0 and 'id="fig-simulation"' not in (tmp_path / "t.html").read_text()


@pytest.mark.slow
def test_states_are_written_only_with_trajectories() -> None:
    cert = F.certified_certificate()
    assert all(run.x for run in cert.checks["simulation"].runs)
    lean = json.loads(cert.to_json())
    full = json.loads(cert.to_json(trajectories=True))
    assert all(r["x"] == [] and r["xhat"] == [] for r in lean["checks"]["simulation"]["runs"])
    back = Certificate.from_dict(full)
    assert [r.x for r in back.checks["simulation"].runs] == \
        [r.x for r in cert.checks["simulation"].runs]
    keys = [f.key for f in figmod.render_figures(back, dpi=30, trajectories=True)]
    assert "simulation" in keys
    assert Certificate.from_dict(full).to_json(trajectories=True) == \
        cert.to_json(trajectories=True)
    # the report writer passes the request on to the JSON
    for asked in (False, True):
        data = json.loads(render_reports(cert, json=True, trajectories=asked)["json"])
        assert all(bool(r["x"]) == asked for r in data["checks"]["simulation"]["runs"])
