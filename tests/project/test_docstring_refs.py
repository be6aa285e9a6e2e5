"""Every `certify.x.y` a docstring or comment cites names a module, or an attribute of one,
that exists: a reference to a module that was moved or renamed is a broken signpost."""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
REF = re.compile(r"`(certify\.[A-Za-z_][A-Za-z_.]*)`")
#: names that are not Python objects (file keys, record names)
NOT_CODE = {"certify.structure"}


def _resolves(name: str) -> bool:
    parts = name.rstrip(".").split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            fields = ({f.name for f in dataclasses.fields(obj)}
                      if dataclasses.is_dataclass(obj) else set())
            if not hasattr(obj, attr) and attr not in fields:
                return False
            obj = getattr(obj, attr, None)
        return True
    return False


def test_cited_modules_exist() -> None:
    broken = []
    for package in ("certify", "training", "reports"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for name in set(REF.findall(path.read_text())):
                if name not in NOT_CODE and not _resolves(name):
                    broken.append(f"{path.relative_to(ROOT)}: {name}")
    assert not broken, "docstrings cite what does not exist:\n" + "\n".join(broken)
