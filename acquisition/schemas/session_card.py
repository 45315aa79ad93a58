"""What a session says about itself: ``session.json`` beside its parts and the same fields in each part's
``vslab.session`` metadata record. Schema-versioned JSON, one reader for every version.

Version 2 (this one) stores every value that is not a string as JSON (``parameters``: the plan's
parameters as a JSON object), names the session's experiment under ``experiment`` and says its
``schema_version``. Version 1 (no ``schema_version``) wrote the parameters with Python's ``repr`` (still
read: ``ast.literal_eval``, literals only, nothing runs) and the experiment under ``protocol``, a word vslab
keeps for wire protocols: :func:`as_current` reads a version-1 card as a version-2 one.
"""

from __future__ import annotations

import ast
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from acquisition.errors import AcquisitionError
from acquisition.storage import as_path

SCHEMA_VERSION = 2
SESSION_CARD = "session.json"  # beside the parts
SESSION_METADATA = "vslab.session"  # the metadata record in every part
COUNTERS_METADATA = "vslab.counters"  # the final stream counters, in the last part
# A card's status: recording (or torn), complete, refused (a simulated plan refused at its start: its
# session holds the COMMAND_REFUSED / SAFETY_STOP events and nothing ran; a rerun runs it again) or
# interrupted (a simulated batch stopped part-way: whole as far as it went, never taken for its plan's)
STATUSES = ("recording", "complete", "refused", "interrupted")
RECOVERED_SUFFIX = ".recovered.mcap"  # a torn part's mended copy, beside it (`vslab sessions recover`)


class SessionCardError(AcquisitionError, ValueError):
    """Session metadata this version of vslab cannot read (a newer schema, unreadable parameters)."""


def as_metadata(fields: Mapping[str, Any]) -> dict[str, str]:
    """Fields as an MCAP metadata map (strings only): strings as they are, anything else as JSON."""
    return {k: v if isinstance(v, str) else json.dumps(v, sort_keys=True) for k, v in fields.items()}


def schema_version(fields: Mapping[str, Any]) -> int:
    """The schema version of a card or metadata map (1 where none is written); newer than this vslab
    knows: ``SessionCardError``."""
    raw = fields.get("schema_version", 1)
    try:
        version = int(raw)
    except (TypeError, ValueError):
        raise SessionCardError(f"schema_version {raw!r} is not a whole number") from None
    if version > SCHEMA_VERSION:
        raise SessionCardError(
            f"written by a newer vslab (session schema {version}; this one reads up to {SCHEMA_VERSION}): "
            "update vslab"
        )
    return version


def as_current(fields: Mapping[str, Any]) -> dict:
    """A card or metadata map of any schema version with the current keys (``experiment``)."""
    out = dict(fields)
    if "experiment" not in out and "protocol" in out:  # version 1
        out["experiment"] = out.pop("protocol")
    return out


def session_parameters(fields: Mapping[str, Any]) -> dict:
    """The plan parameters of a session's metadata (``{}`` where it has none), of any schema version."""
    raw = fields.get("parameters")
    if raw is None:
        return {}
    if not isinstance(raw, str):
        return dict(raw)
    try:
        value = json.loads(raw) if schema_version(fields) >= 2 else ast.literal_eval(raw)
    except (ValueError, SyntaxError) as exc:
        raise SessionCardError(f"unreadable parameters ({type(exc).__name__}: {exc})") from exc
    if not isinstance(value, dict):
        raise SessionCardError(f"parameters are a {type(value).__name__}, not a mapping")
    return value


def recovered_path(part: Path) -> Path:
    """Where the mended copy of a torn ``part`` goes (and is looked for)."""
    return part.with_name(part.name.removesuffix(".mcap") + RECOVERED_SUFFIX)


def _empty(part: Path) -> bool:
    try:
        return part.stat().st_size == 0
    except OSError:
        return False


def readable_parts(directory: Path) -> list[Path]:
    """A session's parts in order: each ``<id>_NNN.mcap``, or its recovered copy where one exists. Empty
    parts after the last one with data (a writer that died opening a new part) are no part of it."""
    parts = sorted(p for p in as_path(directory).glob("*.mcap") if not p.name.endswith(RECOVERED_SUFFIX))
    while len(parts) > 1 and _empty(parts[-1]) and not _empty(parts[0]):
        parts.pop()
    return [recovered_path(p) if recovered_path(p).is_file() else p for p in parts]
