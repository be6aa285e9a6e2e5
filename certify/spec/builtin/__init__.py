"""The built-in system specs shipped with the package (`<name>.toml` beside this file).

Reading them imports nothing heavy (no sympy, no torch), so the command line can list and
print them, and suggest a name, before any numerical library loads.
"""

from __future__ import annotations

from importlib import resources

__all__ = ["names", "text"]


def names() -> list[str]:
    """Names of the shipped systems, sorted."""
    folder = resources.files(__name__)
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def text(name: str) -> str:
    """The TOML text of the shipped system `name` (FileNotFoundError if there is none)."""
    return (resources.files(__name__) / f"{name}.toml").read_text()
