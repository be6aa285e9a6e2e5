"""Reports: pure renderers of a `certify.certificate.Certificate`.

Public API:
    write_reports(certificate, *, html=, pdf=, junit=, json=)  -- atomic files
    render_reports(certificate, *, html=, pdf=, junit=, json=) -- bytes in memory
    render_html(certificate) -> str     -- one self-contained HTML file
    render_pdf(certificate) -> bytes    -- multi-page PDF, selectable text
    render_junit(certificate) -> str    -- JUnit XML, one test case per check
    render_figures(certificate)         -- the figures as PNG (shared by HTML and PDF)

Names are imported on first use (PEP 562): matplotlib loads only when a figure is drawn, so
`reports.content` (the terminal summary) and JUnit/JSON output stay light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_PUBLIC = {"render_figures": "reports.figures", "render_html": "reports.html",
           "render_junit": "reports.junit", "render_pdf": "reports.pdf",
           "render_reports": "reports.render", "write_reports": "reports.render"}

__all__ = ["render_figures", "render_html", "render_junit", "render_pdf", "render_reports",
           "write_reports"]


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'reports' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


if TYPE_CHECKING:  # pragma: no cover
    from reports.figures import render_figures
    from reports.html import render_html
    from reports.junit import render_junit
    from reports.pdf import render_pdf
    from reports.render import render_reports, write_reports
