"""Reports: pure renderers of a `certify.certificate.Certificate`.

Public API:
    write_reports(certificate, *, html=, pdf=, junit=, json=)  -- atomic files
    render_reports(certificate, *, html=, pdf=, junit=, json=) -- bytes in memory
    render_html(certificate) -> str     -- one self-contained HTML file
    render_pdf(certificate) -> bytes    -- multi-page PDF, selectable text
    render_junit(certificate) -> str    -- JUnit XML, one test case per check
    render_figures(certificate)         -- the figures as PNG (shared by HTML and PDF)
"""

from reports.figures import render_figures
from reports.html import render_html
from reports.junit import render_junit
from reports.pdf import render_pdf
from reports.render import render_reports, write_reports

__all__ = ["render_figures", "render_html", "render_junit", "render_pdf", "render_reports",
           "write_reports"]
