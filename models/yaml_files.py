"""Reading the project's YAML files (robot descriptions, protocols, training grids) with one clear message.

Every problem a user can cause — an unreadable or binary file, YAML that does not parse (with its line), a
value YAML recognises but cannot build (a date like 2024-13-01) — becomes one ``error`` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import yaml


def read_yaml(path: Path, error: type[Exception] = ValueError, shown: str | None = None) -> object:
    """The YAML document in ``path``; any problem raises ``error`` with a one-line message naming ``shown``
    (default: the path)."""
    shown = str(path) if shown is None else shown
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise error(f"{shown}: not a text file (YAML expected)") from None
    except OSError as exc:
        raise error(f"{shown}: cannot be read ({exc.strerror or exc})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}:" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise error(f"{shown}:{where} not valid YAML ({problem})") from None
    except ValueError as exc:  # a value YAML recognises but cannot build (a date like 2024-13-01)
        raise error(f"{shown}: not valid YAML ({exc})") from None
