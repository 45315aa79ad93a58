"""The events topic: plan markers, payload changes, device gaps and operator notes.

Events are rare (a few per repetition), so they carry free text: the one variable-size message of a session,
encoded here field by field in CDR (strings are a uint32 length including the terminating NUL, the UTF-8
bytes and the NUL, aligned to 4).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from acquisition.schemas.cdr import CDR_LE_HEADER, HEADER_SIZE, SchemaError

EVENTS = "/events"  # the topic
EVENT_SCHEMA_NAME = "vslab_msgs/msg/Event"


class EventKind(enum.IntEnum):
    """What happened; the numbers are part of the file format (never renumber)."""

    NOTE = 0  # operator or runner note
    SESSION_START = 1
    SESSION_END = 2
    REPETITION_START = 3  # index = repetition number, label = trial name
    REPETITION_END = 4
    PAYLOAD = 5  # value = payload in kg now hanging at the end-effector
    SETTLED = 6  # the plan waited for settling; index = point number
    DEVICE_GAP_START = 7  # label = device whose worker lost it
    DEVICE_GAP_END = 8  # the worker reconnected; value = gap length in s
    SAFETY_STOP = 9  # label = which limit, text = why
    PLAN_STEP = 10  # index = step number, label = step kind
    COMMAND_REFUSED = 11  # the command guard kept a command from a device; label = device, text = why
    DEVICE_FAULT = 12  # a streaming device reported a fault (a drive's EMCY); label = device, text = it


EVENT_SCHEMA = (
    "# One event of a session. log_time is the host time it happened.\n"
    + "".join(f"uint8 {k.name}={k.value}\n" for k in EventKind)
    + "uint8 kind                      # one of the constants above\n"
    "int32 index                     # repetition, point or step number (-1: none)\n"
    "float64 value                   # SI value the kind defines (payload kg, gap s), NaN if none\n"
    "string label                    # short machine-readable label (trial name, device, limit)\n"
    "string text                     # free text for people\n"
)


@dataclass(frozen=True)
class Event:
    kind: EventKind
    index: int = -1
    value: float = float("nan")
    label: str = ""
    text: str = ""

    def encode(self) -> bytes:
        out = bytearray(CDR_LE_HEADER)
        out += struct.pack("<B3xid", int(self.kind), self.index, self.value)  # 1 + pad 3 + 4 + 8
        for text in (self.label, self.text):
            raw = text.encode("utf-8") + b"\0"
            out += b"\0" * (-(len(out) - HEADER_SIZE) % 4)
            out += struct.pack("<I", len(raw)) + raw
        return bytes(out)

    @classmethod
    def decode(cls, data: bytes) -> Event:
        if data[:HEADER_SIZE] != CDR_LE_HEADER:
            raise SchemaError("event: not a little-endian CDR message")
        kind, index, value = struct.unpack_from("<B3xid", data, HEADER_SIZE)
        pos = HEADER_SIZE + 16
        strings = []
        for _ in range(2):
            pos += -(pos - HEADER_SIZE) % 4
            (length,) = struct.unpack_from("<I", data, pos)
            strings.append(bytes(data[pos + 4 : pos + 4 + length - 1]).decode("utf-8"))
            pos += 4 + length
        return cls(EventKind(kind), index, value, *strings)
