"""`[tool.certify]` in the user's pyproject.toml: the CI gate policy. Flags win over it.

Its keys are the settings' names (`certify.settings.DECLARATIONS`); a retired key
(`certify.settings.RETIRED`) is refused with its replacement, an unknown one with the list
of known ones.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from certify.errors import SettingsError
from certify.settings import (
    DECLARATIONS,
    FIELD_NAMES,
    RETIRED,
    VerifySettings,
    make_settings,
    retired_message,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def find_pyproject(start: Path | None = None) -> Path | None:
    """The nearest pyproject.toml at or above `start` (default: the working directory)."""
    here = (start or Path.cwd()).resolve()
    for folder in (here, *here.parents):
        candidate = folder / "pyproject.toml"
        if candidate.is_file():
            return candidate
    return None


def read_tool_table(path: Path) -> dict[str, Any]:
    """The `[tool.certify]` table of `path` with keys normalised (dashes -> underscores)."""
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: cannot read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"{path}: not valid TOML ({exc})") from None
    table = data.get("tool", {}).get("certify", {})
    if not isinstance(table, dict):
        raise SettingsError(f"{path}: [tool.certify] must be a table")
    return {str(k).replace("-", "_"): v for k, v in table.items()}


#: the command-line flag of each setting that has one, for errors about a flag's value
FLAGS = {d.name: d.flag for d in DECLARATIONS if d.flag}


def load_settings(flags: dict[str, Any], config: Path | None = None,
                  use_pyproject: bool = True) -> tuple[VerifySettings, str | None]:
    """Settings from `[tool.certify]` overridden by `flags` (None values ignored).

    Returns the settings and the path of the configuration file used (if any).
    """
    values: dict[str, Any] = {}
    source = None
    path = config if config is not None else (find_pyproject() if use_pyproject else None)
    if config is not None and not config.is_file():
        raise SettingsError(f"config file {config} not found")
    if path is not None:
        table = read_tool_table(path)
        retired = sorted(set(table) & set(RETIRED))
        if retired:
            raise SettingsError(retired_message(retired[0], f"[tool.certify] in {path}:"))
        unknown = sorted(set(table) - set(FIELD_NAMES))
        if unknown:
            raise SettingsError(f"[tool.certify] in {path}: unknown key(s) {', '.join(unknown)} "
                                f"(known: {', '.join(FIELD_NAMES)})")
        make_settings(table, source="[tool.certify]")  # validate the file on its own
        values.update(table)
        source = str(path) if table else None
    values.update({k: v for k, v in flags.items() if v is not None})
    try:
        return make_settings(values, source="option"), source
    except SettingsError as exc:  # in the words the user typed: the flag, not the field
        text = str(exc)
        for name, flag in FLAGS.items():
            if flags.get(name) is not None and text.startswith(f"option {name} "):
                raise SettingsError(flag + text[len(f"option {name}"):]) from None
        raise
