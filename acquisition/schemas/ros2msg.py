"""Parse a ros2msg schema text back into a fixed-layout message, when it is one."""

from __future__ import annotations

import re

from acquisition.schemas.cdr import PRIMITIVES, Field, FixedMessage

_FIELD = re.compile(
    r"^(?P<type>[A-Za-z0-9_/]+)(?:\[(?P<count>\d*)\])?\s+(?P<name>[A-Za-z_]\w*)\s*(?:#\s*(?P<doc>.*))?$"
)


def parse_fixed_message(name: str, text: str) -> FixedMessage | None:
    """The ``FixedMessage`` a ros2msg text describes, or None if any field is not fixed-size (strings,
    unbounded arrays, nested types). Constants (``uint8 NAME=1``) and comments are skipped."""
    fields = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("=" * 10):  # start of a dependency's definition: not a flat message
            return None
        code = line.split("#", 1)[0]
        if "<=" in code:  # bounded strings and arrays have no fixed layout
            return None
        m = _FIELD.match(line)
        if m is None:
            if "=" in code:  # a constant
                continue
            return None
        kind, count = m["type"], m["count"]
        if kind not in PRIMITIVES or count == "":
            return None
        fields.append(Field(m["name"], kind, int(count) if count else 0, (m["doc"] or "").strip()))
    return FixedMessage(name, tuple(fields)) if fields else None
