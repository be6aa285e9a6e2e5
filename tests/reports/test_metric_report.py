"""The metric that follows the state in the reports: its section (facts and the stages'
table, bounds rounded outward) and the map of its smallest eigenvalue over X, checked
against the eigenvalues computed directly from the polynomial."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from certify.certificate import Certificate
from certify.model.metric import PolyMetric, even_monomials
from certify.results import MetricBoundResult, Status
from reports.figure_kit import drawn
from reports.figures_maps import fig_metric_map, metric_eigenvalues
from reports.html import render_html
from reports.sections import sections

from .builders import headline_certificate


def _metric() -> PolyMetric:
    e = even_monomials(2, 2)
    c = np.zeros((len(e), 2, 2))
    for k, row in enumerate(e.tolist()):
        if row == [0, 0]:
            c[k] = [[2.0, 0.3], [0.3, 1.0]]
        elif row == [1, 1]:
            c[k] = [[0.0, 0.2], [0.2, 0.1]]
        elif row == [2, 0]:
            c[k] = [[0.1, 0.0], [0.0, 0.05]]
    return PolyMetric(e, c)


def metric_certificate() -> Certificate:
    cert = headline_certificate()
    cert.checks["metric_bound"] = MetricBoundResult(
        Status.PROVED, "||e|| <= 1.0612 after the second stage",
        metric=_metric().to_dict(), m_min=0.41234567, a=3.2, gamma_h=1.0, gamma=[1.0, 0.0],
        stages=[dict(tau=0.61234567, alpha=0.83333333, mu=0.17777777, entry=1.0, v_inf=0.1,
                     boxes=1234, duration=2.0)],
        plant_box=[[-1.35, 1.35], [-1.21, 1.21]], ultimate=1.0612, boxes=1234)
    return cert


def test_the_section_shows_the_stages_rounded_outward():
    cert = Certificate.from_dict(json.loads(metric_certificate().to_json()))
    sec = next(s for s in sections(cert) if s.anchor == "metric_bound")
    assert sec.status == "PROVED" and "M(x)" in sec.paragraphs[0]
    (table,) = sec.tables
    (row,) = table.rows
    assert row[0] == "2" and row[4] == "1234"
    assert float(row[1]) >= 0.61234567 and float(row[3]) >= 0.17777777  # upper bounds
    assert float(row[2]) <= 0.83333333  # a lower bound
    html = render_html(cert)
    assert 'id="metric_bound"' in html or "Metric M(x)" in html


@pytest.mark.parametrize("point", [(-1.0, 2.0), (0.3, -0.7), (2.0, 3.0)])
def test_the_eigenvalues_drawn_are_those_of_the_polynomial(point):
    m = _metric()
    lo, hi = metric_eigenvalues(m.to_dict(), np.array([point[0]]), np.array([point[1]]),
                                np.zeros(2))
    M = m.value(torch.tensor([point], dtype=torch.float64))[0].numpy()
    w = np.linalg.eigvalsh(M)
    assert lo[0, 0] == pytest.approx(w[0], rel=1e-12, abs=1e-12)
    assert hi[0, 0] == pytest.approx(w[-1], rel=1e-12, abs=1e-12)


def test_the_map_outlines_the_plant_box_and_is_absent_without_a_metric():
    cert = metric_certificate()
    fig = fig_metric_map(cert)
    assert fig is not None and "plant box" in drawn(fig)
    cert.checks["metric_bound"] = MetricBoundResult(Status.NOT_APPLICABLE, "not applicable")
    assert fig_metric_map(cert) is None
    bad = metric_certificate()
    bad.checks["metric_bound"].metric = {"exponents": [[0]], "coefficients": "x"}
    assert fig_metric_map(bad) is None
