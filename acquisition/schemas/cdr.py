"""Fixed-layout ROS 2 messages in CDR: one numpy structured dtype per message, encoded and decoded in bulk.

A ros2msg definition made only of fixed-size fields (numbers, bools and fixed-length arrays of them) has a
fixed CDR layout: a 4-byte encapsulation header (CDR little-endian), then each field aligned to its own size,
counted from the end of the header. So a message is one row of a structured array: the recorder encodes a
batch with one ``tobytes`` and the pipeline decodes a chunk with one ``frombuffer``. mcap-ros2-support's
generic decoder reads the same bytes (the tests use it as the oracle).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from acquisition.errors import AcquisitionError

CDR_LE_HEADER = b"\x00\x01\x00\x00"  # encapsulation: CDR, little-endian, options 0
HEADER_SIZE = len(CDR_LE_HEADER)

PRIMITIVES: dict[str, str] = {
    "bool": "?",
    "int8": "i1",
    "uint8": "u1",
    "int16": "<i2",
    "uint16": "<u2",
    "int32": "<i4",
    "uint32": "<u4",
    "int64": "<i8",
    "uint64": "<u8",
    "float32": "<f4",
    "float64": "<f8",
}


class SchemaError(AcquisitionError, ValueError):
    """A message definition that is not a fixed-layout ros2msg, or values that do not fit it."""


@dataclass(frozen=True)
class Field:
    """One field: ``float64[3] position`` is Field("position", "float64", 3); count 0 means a scalar."""

    name: str
    type: str
    count: int = 0
    doc: str = ""

    def __post_init__(self) -> None:
        if self.type not in PRIMITIVES:
            raise SchemaError(f"field {self.name}: {self.type!r} is not a fixed-size ros2 primitive")
        if self.count < 0:
            raise SchemaError(f"field {self.name}: array length must be ≥ 1, got {self.count}")

    @property
    def ros2msg(self) -> str:
        kind = f"{self.type}[{self.count}]" if self.count else self.type
        line = f"{kind} {self.name}"
        return f"{line:<32}# {self.doc}" if self.doc else line


@dataclass(frozen=True)
class FixedMessage:
    """A ros2msg message type of fixed-size fields, e.g. ``vslab_msgs/msg/ServoState``."""

    name: str
    fields: tuple[Field, ...]
    doc: str = ""

    @property
    def ros2msg(self) -> str:
        """The schema text stored in the MCAP file (comments carry units)."""
        head = [f"# {line}" for line in self.doc.splitlines()]
        return "\n".join([*head, *(f.ros2msg for f in self.fields)]) + "\n"

    @cached_property
    def dtype(self) -> np.dtype:
        """Structured dtype of one encoded message, header included (field ``_cdr_header``)."""
        names, formats, offsets = ["_cdr_header"], [("u1", HEADER_SIZE)], [0]
        position = 0
        for f in self.fields:
            base = np.dtype(PRIMITIVES[f.type])
            position = -(-position // base.itemsize) * base.itemsize  # align to the primitive's size
            names.append(f.name)
            formats.append((base, (f.count,)) if f.count else base)
            offsets.append(HEADER_SIZE + position)
            position += base.itemsize * max(f.count, 1)
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": HEADER_SIZE + position}
        )

    @cached_property
    def field_mask(self) -> np.ndarray:
        """0xFF on every byte of a field, 0 on alignment padding: ``raw & mask`` zeroes the padding, which
        numpy copies of structured rows (fancy indexing) leave uninitialised."""
        mask = np.zeros(self.size, dtype=np.uint8)
        for name in self.dtype.names:
            sub, offset = self.dtype.fields[name][:2]
            mask[offset : offset + sub.itemsize] = 0xFF
        return mask

    def canonical_bytes(self, rows: np.ndarray) -> np.ndarray:
        """(n, size) uint8 of ``rows`` with zeroed padding: what goes on the wire."""
        return np.ascontiguousarray(rows).view(np.uint8).reshape(len(rows), self.size) & self.field_mask

    @property
    def size(self) -> int:
        """Bytes per encoded message."""
        return self.dtype.itemsize

    def empty(self, n: int) -> np.ndarray:
        """``n`` zeroed messages with the encapsulation header set, ready to fill column by column."""
        rows = np.zeros(n, dtype=self.dtype)
        rows["_cdr_header"] = np.frombuffer(CDR_LE_HEADER, dtype=np.uint8)
        return rows

    def pack(self, columns: Mapping[str, object], n: int | None = None) -> np.ndarray:
        """Messages from columns (arrays with a leading message axis, or scalars broadcast to all)."""
        unknown = set(columns) - set(self.dtype.names)
        if unknown:
            raise SchemaError(f"{self.name} has no field(s) {sorted(unknown)}")
        if n is None:
            n = self._count(columns)
        rows = self.empty(n)
        for name, values in columns.items():
            try:
                rows[name] = values
            except (ValueError, TypeError) as exc:
                raise SchemaError(f"{self.name}.{name}: {exc}") from exc
        return rows

    def _count(self, columns: Mapping[str, object]) -> int:
        """Number of messages in columns: the leading axis of any value with one more axis than its field."""
        by_name = {f.name: f for f in self.fields}
        lengths = set()
        for name, values in columns.items():
            field = by_name.get(name)
            if field is not None and np.ndim(values) == (1 if field.count else 0) + 1:
                lengths.add(len(values))  # type: ignore[arg-type]
        if len(lengths) > 1:
            raise SchemaError(f"{self.name}: columns of different lengths {sorted(lengths)}")
        return lengths.pop() if lengths else 1

    def encode(self, **values: object) -> bytes:
        """One message's bytes."""
        return self.pack(values, n=1).tobytes()

    def decode(self, data: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
        """Messages back from their concatenated bytes (or an (n, size) uint8 array)."""
        buf = np.asarray(data, dtype=np.uint8).reshape(-1) if isinstance(data, np.ndarray) else data
        if len(buf) % self.size:
            raise SchemaError(
                f"{self.name}: {len(buf)} bytes is not a whole number of {self.size}-byte messages"
            )
        return np.frombuffer(buf, dtype=self.dtype)
