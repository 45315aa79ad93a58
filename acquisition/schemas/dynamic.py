"""Any ros2msg message decoded from CDR, field by field: the generic path for topics without a fixed layout.

A schema text (the message's own fields, then each type it uses after a ``====`` line and ``MSG: pkg/Type``,
as ROS 2 tools store it in MCAP) becomes a ``DynamicMessage`` whose ``decode`` turns one CDR payload into a
dict (nested messages as dicts, arrays as lists, strings as str). Correct, not fast: the recorder's topics
take the fixed-layout path (``cdr.FixedMessage``) and the events topic its own codec; this is for topics
other tools wrote. mcap-ros2-support decodes the same bytes (the tests' oracle, not a dependency).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from acquisition.schemas.cdr import HEADER_SIZE, SchemaError

FORMATS: dict[str, str] = {  # struct format of each primitive (CDR aligns each to its own size)
    "bool": "?", "byte": "B", "char": "B", "int8": "b", "uint8": "B", "int16": "h", "uint16": "H",
    "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f", "float64": "d",
}  # fmt: skip
STRINGS = ("string", "wstring")
SEQUENCE = -1  # DynamicField.size of a sequence (unbounded or bounded): its length is on the wire
_TIME = (("int32", "sec"), ("uint32", "nanosec"))
BUILTIN = {"builtin_interfaces/Time": _TIME, "builtin_interfaces/Duration": _TIME}
_ALIASES = {"time": "builtin_interfaces/Time", "duration": "builtin_interfaces/Duration",
            "Header": "std_msgs/Header"}  # fmt: skip
_SEPARATOR = re.compile(r"^={3,}\s*$", re.MULTILINE)
_TYPE = re.compile(r"^(?P<base>[A-Za-z_][\w/]*)(?:<=\d+)?(?:\[(?P<bound><=)?(?P<size>\d*)\])?$")


@dataclass(frozen=True)
class DynamicField:
    """One field: ``type`` is a primitive, ``string``/``wstring`` or a message ``pkg/Type``; ``size`` is None
    for a single value, ``SEQUENCE`` for a sequence (its length on the wire), N for a fixed array of N."""

    name: str
    type: str
    size: int | None = None


def _short(name: str) -> str:
    """``pkg/msg/Type`` → ``pkg/Type`` (both spellings name one message)."""
    parts = name.split("/")
    return f"{parts[0]}/{parts[-1]}" if len(parts) > 1 else name


def _field(line: str, package: str) -> DynamicField | None:
    """One definition line → its field; None for a constant (``uint8 KIND=1``)."""
    tokens = line.split(None, 2)
    if len(tokens) < 2:
        raise SchemaError(f"cannot read the definition line {line!r}")
    kind, name = tokens[0], tokens[1]
    if "=" in name or (len(tokens) > 2 and tokens[2].lstrip().startswith("=")):
        return None
    m = _TYPE.match(kind)
    if m is None:
        raise SchemaError(f"cannot read the type {kind!r} of field {name!r}")
    base = m["base"]
    if base not in FORMATS and base not in STRINGS:
        base = _ALIASES.get(base, base)
        base = _short(base) if "/" in base else f"{package}/{base}"
    size = None if "[" not in kind else (SEQUENCE if m["bound"] or not m["size"] else int(m["size"]))
    return DynamicField(name, base, size)


def parse_definitions(schema_name: str, text: str) -> dict[str, tuple[DynamicField, ...]]:
    """Every message of a ros2msg schema text by its ``pkg/Type`` name (the first: ``schema_name``)."""
    definitions: dict[str, tuple[DynamicField, ...]] = {
        name: tuple(DynamicField(n, t) for t, n in fields) for name, fields in BUILTIN.items()
    }
    current = _short(schema_name)
    for section in _SEPARATOR.split(text):
        lines = [ln.split("#", 1)[0].strip() for ln in section.splitlines()]
        lines = [ln for ln in lines if ln]
        if lines and lines[0].startswith("MSG:"):
            current = _short(lines[0][4:].strip())
            lines = lines[1:]
        package = current.split("/")[0]
        fields = [f for f in (_field(ln, package) for ln in lines) if f is not None]
        definitions[current] = tuple(fields)
    return definitions


class _Reader:
    """A CDR payload read front to back; alignment counts from the end of the encapsulation header."""

    def __init__(self, data: bytes) -> None:
        if len(data) < HEADER_SIZE:
            raise SchemaError(f"a CDR message has a {HEADER_SIZE}-byte header; got {len(data)} bytes")
        kind = data[1]
        if data[0] != 0 or kind > 1:
            raise SchemaError(f"unsupported CDR encapsulation {bytes(data[:2]).hex()} (plain CDR only)")
        self.data, self.pos, self.endian = memoryview(data), HEADER_SIZE, "<" if kind == 1 else ">"

    def values(self, fmt: str, n: int) -> tuple:
        if n == 0:  # nothing read, nothing aligned
            return ()
        size = struct.calcsize(fmt)
        self.pos += -(self.pos - HEADER_SIZE) % size
        if self.pos + size * n > len(self.data):
            raise SchemaError(f"message cut short: {n} × {fmt!r} at byte {self.pos} of {len(self.data)}")
        out = struct.unpack_from(f"{self.endian}{n}{fmt}", self.data, self.pos)
        self.pos += size * n
        return out

    def count(self, least_bytes: int) -> int:
        """A sequence's length, checked against the bytes left (each element takes ``least_bytes``)."""
        (n,) = self.values("I", 1)
        if n * least_bytes > len(self.data) - self.pos:
            raise SchemaError(f"sequence of {n} elements at byte {self.pos} is longer than the message")
        return n

    def string(self) -> str:
        n = self.count(1)
        raw = bytes(self.data[self.pos : self.pos + n])
        self.pos += n
        try:
            return raw.rstrip(b"\0").decode("utf-8")
        except UnicodeDecodeError as exc:
            raise SchemaError(f"string at byte {self.pos - n} is not UTF-8") from exc


class DynamicMessage:
    """A ros2msg message of any layout: ``DynamicMessage(name, text).decode(payload)`` → dict."""

    def __init__(self, schema_name: str, text: str) -> None:
        self.name = _short(schema_name)
        self.definitions = parse_definitions(schema_name, text)
        self._check(self.name, ())

    def _check(self, name: str, seen: tuple[str, ...]) -> None:
        """Every type used is defined, and no message contains itself."""
        if name not in self.definitions:
            raise SchemaError(f"{self.name}: no definition of {name!r} in the schema")
        if name in seen:
            raise SchemaError(f"{self.name}: {name} contains itself")
        for f in self.definitions[name]:
            if f.type == "wstring":
                raise SchemaError(f"{self.name}.{f.name}: wstring fields are not supported")
            if f.type not in FORMATS and f.type not in STRINGS:
                self._check(f.type, (*seen, name))

    def decode(self, data: bytes | bytearray | memoryview) -> dict:
        """One CDR payload (header included) → {field: value}; ``SchemaError`` if it does not fit."""
        return self._message(self.name, _Reader(bytes(data)))

    def _message(self, name: str, reader: _Reader) -> dict:
        fields = self.definitions[name]
        if not fields:  # ROS 2 gives an empty message one uint8 member
            reader.values("B", 1)
            return {}
        return {f.name: self._field(f, reader) for f in fields}

    def _field(self, f: DynamicField, reader: _Reader):
        if f.size is None:
            return self._one(f.type, reader)
        n = f.size if f.size != SEQUENCE else reader.count(struct.calcsize(FORMATS.get(f.type, "B")))
        if f.type in FORMATS:
            return list(reader.values(FORMATS[f.type], n))
        return [self._one(f.type, reader) for _ in range(n)]

    def _one(self, kind: str, reader: _Reader):
        if kind in FORMATS:
            return reader.values(FORMATS[kind], 1)[0]
        if kind == "string":
            return reader.string()
        return self._message(kind, reader)
