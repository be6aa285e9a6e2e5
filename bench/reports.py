"""The reports of a certificate: what they cost to render and how big the JSON is.

One JSON line per (tree, example), comparing two source trees side by side in one session
(default: `/work/main` as "before" and this tree as "after"), each in subprocesses with
PYTHONPATH set to its tree. Each tree renders certificates it wrote itself: `certify run
examples/X.ckpt --quiet --json` once per tree and example (cached in `--certs`, reused on
the next run of this script), so "after" measures what a run of the new code writes.

Per (tree, example), medians over `--repeat` worker processes, wall and CPU seconds:

- `run_added_s`: the first `render_reports` of all four reports (HTML, PDF, JUnit, JSON) in
  a process that has already imported `certify.verify` (torch), as at the end of `certify
  run`: what the reports add to a run, their imports (matplotlib, jinja2) included;
- stages, warm (the same process again): `figures_s` (build and PNG per figure in
  `figure_s`), `html_s` (template), `pdf_s` (page layout), `junit_s`, `json_s`;
- `cli_report_s`: wall seconds of `certify report X.json --html --pdf --junit --json`, a
  fresh interpreter (imports of torch and matplotlib included);
- sizes: `json_bytes`, `json_lines`, `html_bytes`, `pdf_bytes`, PNG bytes per figure;
- `report-maps` lines (with `--maps`, this tree only): seconds of `certify.verify.report_maps`
  (the run's "figures" step, the maps the reports draw) on the example's checkpoint at 61 and
  at 41 points per axis.

The trees' modules are byte-compiled once into a cache of this script
(`PYTHONPYCACHEPREFIX`, as an installed package has them) and each measurement is preceded
by one untimed run, so no number includes compiling Python sources.

Runs of the two trees alternate, so load from other processes hits both alike; `load` is
the 1-minute load average when the line was printed. Wall seconds on a shared machine are
noisy: compare CPU seconds and ratios, and re-run when other work was going on.

Run: python bench/reports.py [--before /work/main] [--after .] [--repeat 3]
         [--only vdp_lmi,lorenz_lmi] [--certs /tmp/certify-bench-reports]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ("vdp", "vdp_certified", "vdp_lmi", "vdp2_lmi", "lorenz_lmi")


def emit(**record: object) -> None:
    from record import emit as record_line  # bench/record.py

    record_line(record)


PYCACHE = Path(tempfile.gettempdir()) / "certify-bench-reports-pycache"


def _env(tree: Path) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1",
           "MPLBACKEND": "Agg", "PYTHONPYCACHEPREFIX": str(PYCACHE)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def make_certificate(tree: Path, example: str, out: Path) -> None:
    """`certify run examples/EXAMPLE.ckpt --quiet --json OUT` with `tree`'s code."""
    if out.is_file():
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = ROOT / "examples" / f"{example}.ckpt"
    proc = subprocess.run([sys.executable, "-m", "certify", "run", str(ckpt), "--quiet",
                           "--json", str(out)], cwd=tempfile.gettempdir(), env=_env(tree),
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode not in (0, 1, 3) or not out.is_file():
        raise SystemExit(f"certify run {example} with {tree} failed ({proc.returncode}): "
                         f"{proc.stderr[-500:]}")


# ----------------------------------------------------------------------------- worker
def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def _since(t: tuple[float, float]) -> tuple[float, float]:
    w, c = _clock()
    return w - t[0], c - t[1]


def worker(cert_path: str) -> None:
    """In this process: a cold render of all four reports (torch already imported, as in a
    run), then each stage once more, warm. Prints one JSON object."""
    here = Path(__file__).resolve().parent  # this file's folder would shadow `reports`
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != here]
    import certify.verify  # noqa: F401  (torch and the checks, as a run has them)
    from certify.certificate import Certificate

    cert = Certificate.load(cert_path)
    t = _clock()
    from reports.render import render_reports

    data = render_reports(cert, html=True, pdf=True, junit=True, json=True)
    cold = _since(t)

    import contextlib

    import matplotlib

    import reports.render
    from reports import figures as F
    from reports.html import render_html
    from reports.junit import render_junit
    from reports.pdf import render_pdf

    # the stages under the collector policy `render_reports` has (if any)
    policy = getattr(reports.render, "_no_cycle_collection", contextlib.nullcontext)
    per_fig: dict[str, tuple[float, float]] = {}
    png_bytes: dict[str, int] = {}
    t = _clock()
    with policy(), matplotlib.rc_context(F.STYLE):
        for spec in F.FIGURES:
            if spec.on_request:
                continue
            t1 = _clock()
            fig = spec.build(cert)
            if fig is None:
                continue
            png = F.figure_png(fig, 150)
            per_fig[spec.key] = _since(t1)
            png_bytes[spec.key] = len(png)
    figs_t = _since(t)
    figures = F.render_figures(cert)
    stages = {}
    for name, fn in (("html", lambda: render_html(cert, figures)),
                     ("pdf", lambda: render_pdf(cert, figures)),
                     ("junit", lambda: render_junit(cert)),
                     ("json", lambda: cert.to_json())):
        with policy():
            t = _clock()
            fn()
            stages[name] = _since(t)
    print(json.dumps({
        "run_added": cold, "figures": figs_t, "figure": per_fig, "png_bytes": png_bytes,
        **stages, "html_bytes": len(data["html"]), "pdf_bytes": len(data["pdf"]),
    }))


def maps_worker(ckpt_path: str, cert_path: str, repeat: int) -> None:
    """Seconds of `report_maps` (the run's "figures" step) at 61 and 41 points per axis."""
    import certify.verify as V
    from certify.certificate import Certificate
    from certify.figuredata import FigureData
    from certify.model import checkpoint

    problem = checkpoint.load(ckpt_path).problem
    checks = Certificate.load(cert_path).checks
    out = {}
    for points in (61, 41):
        V.MAP_RESOLUTION = points
        V.report_maps(problem, checks, FigureData())  # untimed: warm
        times = []
        for _ in range(repeat):
            t = _clock()
            V.report_maps(problem, checks, FigureData())
            times.append(_since(t))
        out[str(points)] = {"wall": _med([w for w, _ in times]),
                            "cpu": _med([c for _, c in times])}
    print(json.dumps(out))


# ----------------------------------------------------------------------------- driver
def _worker_once(tree: Path, cert: Path) -> dict:
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker",
                           str(cert)], cwd=tempfile.gettempdir(), env=_env(tree),
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"worker failed on {cert} with {tree}: {proc.stderr[-800:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _cli_report(tree: Path, cert: Path) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "certify", "report", str(cert), "--quiet",
                               "--html", str(d / "r.html"), "--pdf", str(d / "r.pdf"),
                               "--junit", str(d / "r.xml"), "--json", str(d / "r.json")],
                              cwd=tmp, env=_env(tree), capture_output=True, text=True,
                              timeout=1800)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"certify report {cert} with {tree} failed: {proc.stderr[-800:]}")
    return wall


def _med(values: list[float]) -> float:
    return round(statistics.median(values), 3)


def _pairs(samples: list[tuple[float, float]]) -> dict[str, float]:
    return {"wall": _med([s[0] for s in samples]), "cpu": _med([s[1] for s in samples])}


def measure(tree: Path, label: str, example: str, cert: Path, repeat: int) -> dict:
    _worker_once(tree, cert)  # untimed: byte-compiles, fills the caches
    runs = [_worker_once(tree, cert) for _ in range(repeat)]
    cli = [_cli_report(tree, cert) for _ in range(repeat)]
    text = cert.read_text()
    keys = sorted({k for r in runs for k in r["figure"]})
    record = {
        "bench": "reports", "tree": label, "path": str(tree), "example": example,
        "json_bytes": len(text.encode()), "json_lines": text.count("\n"),
        "run_added_s": _pairs([r["run_added"] for r in runs]),
        "figures_s": _pairs([r["figures"] for r in runs]),
        "figure_s": {k: _pairs([r["figure"][k] for r in runs if k in r["figure"]])
                     for k in keys},
        **{f"{s}_s": _pairs([r[s] for r in runs]) for s in ("html", "pdf", "junit", "json")},
        "cli_report_s": _med(cli), "html_bytes": runs[0]["html_bytes"],
        "pdf_bytes": runs[0]["pdf_bytes"], "png_bytes": runs[0]["png_bytes"],
        "repeat": repeat, "load": round(os.getloadavg()[0], 2),
    }
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--maps-worker", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--maps", action="store_true",
                    help="also time the maps of the run's figures step (this tree only)")
    ap.add_argument("--before", default="/work/main", help="the reference tree ('' to skip)")
    ap.add_argument("--after", default=str(ROOT))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default=",".join(EXAMPLES))
    ap.add_argument("--certs", default=str(Path(tempfile.gettempdir())
                                           / "certify-bench-reports"),
                    help="where each tree's certificates are written once and reused")
    args = ap.parse_args()
    if args.worker:
        worker(args.worker)
        return
    if args.maps_worker:
        maps_worker(*args.maps_worker, repeat=args.repeat)
        return
    trees = [(label, Path(p).resolve()) for label, p in (("before", args.before),
                                                         ("after", args.after)) if p]
    certs = Path(args.certs)
    results: dict[tuple[str, str], dict] = {}
    for example in [e for e in args.only.split(",") if e]:
        for label, tree in trees:
            path = certs / label / f"{example}.json"
            make_certificate(tree, example, path)
            results[(label, example)] = rec = measure(tree, label, example, path, args.repeat)
            emit(**rec)
        if len(trees) == 2:
            b, a = results[("before", example)], results[("after", example)]
            emit(bench="reports-compare", example=example,
                 json_bytes=[b["json_bytes"], a["json_bytes"]],
                 run_added_wall_s=[b["run_added_s"]["wall"], a["run_added_s"]["wall"]],
                 run_added_cpu_s=[b["run_added_s"]["cpu"], a["run_added_s"]["cpu"]],
                 cli_report_s=[b["cli_report_s"], a["cli_report_s"]],
                 ratio_cpu=round(a["run_added_s"]["cpu"] / max(b["run_added_s"]["cpu"], 1e-9),
                                 3),
                 load=round(os.getloadavg()[0], 2))
        if args.maps:
            label, tree = trees[-1]
            proc = subprocess.run(
                [sys.executable, str(Path(__file__).resolve()), "--maps-worker",
                 str(ROOT / "examples" / f"{example}.ckpt"),
                 str(certs / label / f"{example}.json"), "--repeat", str(args.repeat)],
                cwd=tempfile.gettempdir(), env=_env(tree), capture_output=True, text=True,
                timeout=1800)
            if proc.returncode != 0:
                raise SystemExit(f"maps worker failed on {example}: {proc.stderr[-800:]}")
            emit(bench="report-maps", tree=label, example=example,
                 seconds=json.loads(proc.stdout.strip().splitlines()[-1]),
                 load=round(os.getloadavg()[0], 2))


if __name__ == "__main__":
    main()
