"""The house rules, checked on the import graph: no cycles, no upward imports, no private
names across modules (every import counts, those inside functions and under TYPE_CHECKING too).

Layers, lowest first: certify.arith < spec < model < enclose < search < prove < design,
simulate < checks < the top-level public surface (verify, certificate) < cli. The base modules
(errors, results, settings, progress, presentation, figuredata, files, budget) are importable
from anywhere. `training` imports certify but never its CLI or `reports`; `reports` imports
only the certificate and result types and the small I/O helper.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("certify", "training", "reports")
ORDER = ("arith", "spec", "model", "enclose", "search", "prove", "design", "simulate",
         "checks")
BASE = {"certify", "certify.errors", "certify.results", "certify.settings", "certify.progress",
        "certify.presentation", "certify.figuredata", "certify.files", "certify.budget"}
REPORTS_MAY_IMPORT = {"certify.certificate", "certify.results", "certify.presentation",
                      "certify.figuredata", "certify.files", "certify.errors"}
#: private names of the enclosure stages still imported across their modules (to go)


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            rel = path.relative_to(ROOT).with_suffix("")
            name = ".".join(rel.parts)
            out[name.removesuffix(".__init__")] = path
    return out


def imports(name: str, path: Path, known: dict[str, Path]) -> list[tuple[str, list[str]]]:
    """(imported module, names imported from it) for every import statement."""
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names if a.name.split(".")[0] in PACKAGES]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] not in PACKAGES:
                continue
            names = [a.name for a in node.names]
            subs = [f"{mod}.{n}" for n in names if f"{mod}.{n}" in known]
            out.append((mod, [n for n in names if f"{mod}.{n}" not in known]))
            out += [(s, []) for s in subs]
    return out


def graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    known = modules()
    edges: dict[str, set[str]] = {m: set() for m in known}
    private = []
    for name, path in known.items():
        for mod, names in imports(name, path, known):
            if mod in known and mod != name and not mod.startswith(name + "."):
                edges[name].add(mod)
            private += [(name, mod, n) for n in names
                        if n.startswith("_") and not n.startswith("__") and mod != name]
    return edges, private


def layer(mod: str) -> tuple[str, int]:
    parts = mod.split(".")
    if parts[0] != "certify":
        return parts[0], 150
    if mod == "certify.__main__":
        return "cli", 200
    if mod in BASE:
        return "base", -1
    if len(parts) > 1 and parts[1] in ORDER:
        return parts[1], ORDER.index(parts[1])
    if len(parts) > 1 and parts[1] == "cli":
        return "cli", 200
    return "top", 100


def test_no_import_cycles():
    edges, _ = graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in edges:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_imports_point_down_the_layers():
    edges, _ = graph()
    bad = []
    for a, targets in edges.items():
        la = layer(a)
        for b in targets:
            lb = layer(b)
            if lb[0] == "base":
                continue
            if la[0] == "reports":
                if b.startswith("certify") and b not in REPORTS_MAY_IMPORT:
                    bad.append((a, b))
            elif la[0] == "training":
                if b.startswith(("certify.cli", "reports")):
                    bad.append((a, b))
            elif la[0] in ORDER and (lb[1] > la[1] or lb[0] in ("training", "reports")):
                bad.append((a, b))
            elif la[0] == "top" and b.startswith(("certify.cli", "training", "reports")):
                bad.append((a, b))
    assert not bad, "upward imports:\n" + "\n".join(f"{a} -> {b}" for a, b in sorted(bad))


def test_no_private_names_imported_across_modules():
    _, private = graph()
    private = [(a, m, n) for a, m, n in private]
    assert not private, "private names imported: " + ", ".join(
        f"{a} imports {n} from {m}" for a, m, n in private)
