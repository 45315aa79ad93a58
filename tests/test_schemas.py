"""Fixed-layout CDR messages and the events message, checked against mcap-ros2-support's generic decoder."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from acquisition.schemas.cdr import CDR_LE_HEADER, PRIMITIVES, Field, FixedMessage, SchemaError
from acquisition.schemas.events import EVENT_SCHEMA, EVENT_SCHEMA_NAME, Event, EventKind
from acquisition.schemas.ros2msg import parse_fixed_message
from acquisition.schemas.topics import EVENTS, session_topics
from models.robot import load_robot

ROBOTS = ("vsl", "vsl_rigid", "popup")
_schema_ids = itertools.count(1)  # the decoder factory caches decoders by schema id: one id per schema


def ros2_decoder(name: str, text: str):
    schema = Schema(id=next(_schema_ids), name=name, encoding="ros2msg", data=text.encode())
    decoder = DecoderFactory().decoder_for("cdr", schema)
    assert decoder is not None
    return decoder


def random_columns(message: FixedMessage, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random values covering each field's whole range (floats: normal, with a few specials)."""
    columns = {}
    for f in message.fields:
        shape = (n, f.count) if f.count else (n,)
        dtype = np.dtype(PRIMITIVES[f.type])
        if f.type == "bool":
            values = rng.random(shape) < 0.5
        elif dtype.kind == "f":
            values = rng.normal(scale=1e3, size=shape).astype(dtype)
            values.reshape(-1)[:3] = [np.inf, -0.0, 1e-300 if dtype.itemsize == 8 else 1e-30][: values.size]
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)
        columns[f.name] = values
    return columns


def as_array(value, field: Field) -> np.ndarray:
    """A ros2-decoded value as numpy (the decoder gives uint8 arrays as bytes, other arrays as lists)."""
    if isinstance(value, bytes | bytearray):
        return np.frombuffer(value, dtype=PRIMITIVES[field.type])
    return np.asarray(value, dtype=PRIMITIVES[field.type])


def all_fixed_messages() -> list[tuple[str, str, FixedMessage]]:
    out = []
    for robot in ROBOTS:
        for topic in session_topics(load_robot(robot)).values():
            if topic.message is not None:
                out.append((robot, topic.name, topic.message))
    return out


EVERY_PRIMITIVE = FixedMessage(
    "test_msgs/msg/EveryPrimitive",
    tuple(Field(f"f_{t}", t) for t in PRIMITIVES)  # scalars in a misaligning order
    + tuple(Field(f"a_{t}", t, 3, f"{t} array") for t in reversed(list(PRIMITIVES)))
    + (Field("tail", "uint8"),),
    "Every primitive, scalar and array,\nto exercise the alignment rules.",
)
LONG_NAME = FixedMessage(  # a field line of ≥ 32 characters: its comment follows the name with no space
    "test_msgs/msg/LongName",
    (Field("a_rather_long_field_name_indeed", "float64", 12, "rad"), Field("x", "int8")),
)
MESSAGES = [(f"{r}:{t}", m) for r, t, m in all_fixed_messages()] + [
    ("every_primitive", EVERY_PRIMITIVE),
    ("long_name", LONG_NAME),
]


def test_every_robot_has_the_core_topics():
    for robot in ROBOTS:
        topics = session_topics(load_robot(robot))
        assert EVENTS in topics and topics[EVENTS].message is None
        assert topics[EVENTS].schema_name == EVENT_SCHEMA_NAME
        assert sum(t.message is not None for t in topics.values()) >= 5


@pytest.mark.parametrize(("label", "message"), MESSAGES, ids=[m[0] for m in MESSAGES])
def test_packed_bytes_decode_with_ros2_decoder(label, message, seed=7):
    rng = np.random.default_rng(seed)
    columns = random_columns(message, 20, rng)
    rows = message.pack(columns)
    assert rows.dtype.itemsize == message.size and len(rows) == 20
    data = rows.tobytes()
    decode = ros2_decoder(message.name, message.ros2msg)
    for i in range(len(rows)):
        raw = data[i * message.size : (i + 1) * message.size]
        assert raw[:4] == CDR_LE_HEADER
        decoded = decode(raw)
        for f in message.fields:
            got = as_array(getattr(decoded, f.name), f)
            np.testing.assert_array_equal(got, columns[f.name][i], err_msg=f"{label}.{f.name}[{i}]")
            np.testing.assert_array_equal(got, rows[f.name][i])


@pytest.mark.parametrize(("label", "message"), MESSAGES, ids=[m[0] for m in MESSAGES])
def test_encode_decode_round_trip(label, message):
    rng = np.random.default_rng(11)
    columns = random_columns(message, 5, rng)
    rows = message.pack(columns)
    for source in (rows.tobytes(), bytearray(rows.tobytes()), memoryview(rows.tobytes())):
        back = message.decode(source)
        assert back.dtype == message.dtype
        assert back.tobytes() == rows.tobytes()
    as_matrix = np.frombuffer(rows.tobytes(), np.uint8).reshape(5, message.size)
    assert message.decode(as_matrix).tobytes() == rows.tobytes()
    one = {name: values[2] for name, values in columns.items()}
    encoded = message.encode(**one)
    assert len(encoded) == message.size and encoded == rows[2:3].tobytes()
    (row,) = message.decode(encoded)
    for name, value in one.items():
        np.testing.assert_array_equal(row[name], value)


@pytest.mark.parametrize(("label", "message"), MESSAGES, ids=[m[0] for m in MESSAGES])
def test_parse_reproduces_the_layout(label, message):
    parsed = parse_fixed_message(message.name, message.ros2msg)
    assert parsed is not None
    assert parsed.name == message.name
    assert parsed.dtype == message.dtype
    assert [(f.name, f.type, f.count) for f in parsed.fields] == [
        (f.name, f.type, f.count) for f in message.fields
    ]
    assert [f.doc for f in parsed.fields] == [f.doc for f in message.fields]


def test_pack_broadcasts_scalars_and_sets_the_header():
    message = EVERY_PRIMITIVE
    rows = message.pack({"f_uint32": np.arange(4, dtype=np.uint32), "f_float64": 2.5, "a_int16": [1, 2, 3]})
    assert len(rows) == 4
    assert np.all(rows["f_float64"] == 2.5) and np.all(rows["a_int16"] == [1, 2, 3])
    assert all(bytes(h) == CDR_LE_HEADER for h in rows["_cdr_header"])
    assert message.pack({"f_int8": 1}).shape == (1,)
    assert len(message.empty(3)) == 3 and message.empty(3).tobytes()[:4] == CDR_LE_HEADER


def test_alignment_follows_cdr():
    message = FixedMessage("t/msg/A", (Field("a", "uint8"), Field("b", "float64"), Field("c", "uint16", 3)))
    # header 4 | a @0 | pad to 8 | b @8..16 | c @16..22  (offsets from the end of the header)
    assert message.dtype.fields["a"][1] == 4
    assert message.dtype.fields["b"][1] == 4 + 8
    assert message.dtype.fields["c"][1] == 4 + 16
    assert message.size == 4 + 22


@pytest.mark.parametrize(
    "text",
    [
        "uint32 a\nstring b\n",
        "uint32 a\nfloat64[] b\n",
        "uint32 a\ngeometry_msgs/Point p\n",
        "uint32 a\nPoint p\n",
        "uint32 a\n" + "=" * 80 + "\nMSG: geometry_msgs/Point\nfloat64 x\n",
        "string s\n",
        "wstring s\n",
        "int32 x 5\n",  # a default value: not something the fixed layout carries
        "# only a comment\n",
        "",
    ],
)
def test_parse_rejects_non_fixed_messages(text):
    assert parse_fixed_message("t/msg/X", text) is None


def test_parse_skips_constants_and_comments():
    text = "# header\nuint8 A=1\nint32 B = -2  # note\n\nfloat64[2] x  # m\n"
    parsed = parse_fixed_message("t/msg/C", text)
    assert parsed is not None and [(f.name, f.count, f.doc) for f in parsed.fields] == [("x", 2, "m")]


@pytest.mark.parametrize("line", ["float64[<=3] b", "string<=8 b"])
def test_parse_rejects_bounded_fields(line):
    assert parse_fixed_message("t/msg/X", f"uint32 a\n{line}\n") is None


def test_event_schema_is_not_fixed():
    assert parse_fixed_message(EVENT_SCHEMA_NAME, EVENT_SCHEMA) is None


# ------------------------------------------------------------------------------------------------ events
EVENTS_CASES = [
    Event(EventKind.NOTE),
    Event(EventKind.NOTE, text="hello"),
    Event(EventKind.SESSION_START, 0, 0.0, "", ""),
    Event(EventKind.REPETITION_START, 12, float("nan"), "trial_a", "first of the morning"),
    Event(EventKind.PAYLOAD, -1, 0.25, "payload", "50 g → 250 g, ünïcødé ✓ 日本語 🤖"),
    Event(EventKind.DEVICE_GAP_END, 2**31 - 1, 1.5e-3, "ndi", "x"),
    Event(EventKind.SAFETY_STOP, -(2**31), -math.inf, "a" * 3, "b" * 4),  # lengths at each alignment
    Event(EventKind.PLAN_STEP, 7, 1e300, "ab", "abcde" * 200),
]


def same_event(a: Event, b: Event) -> bool:
    same_value = (math.isnan(a.value) and math.isnan(b.value)) or a.value == b.value
    return (a.kind, a.index, a.label, a.text) == (b.kind, b.index, b.label, b.text) and same_value


@pytest.mark.parametrize("event", EVENTS_CASES, ids=range(len(EVENTS_CASES)))
def test_event_round_trip_and_ros2_decoder(event):
    data = event.encode()
    assert data[:4] == CDR_LE_HEADER
    back = Event.decode(data)
    assert same_event(back, event) and isinstance(back.kind, EventKind)
    decoded = ros2_decoder(EVENT_SCHEMA_NAME, EVENT_SCHEMA)(data)
    assert decoded.kind == int(event.kind)
    assert decoded.index == event.index
    assert (math.isnan(decoded.value) and math.isnan(event.value)) or decoded.value == event.value
    assert decoded.label == event.label and decoded.text == event.text


def test_event_schema_constants_match_kinds():
    for kind in EventKind:
        assert f"uint8 {kind.name}={kind.value}\n" in EVENT_SCHEMA


def test_event_decode_rejects_big_endian():
    data = bytearray(Event(EventKind.NOTE).encode())
    data[1] = 0  # CDR big-endian
    with pytest.raises(SchemaError):
        Event.decode(bytes(data))


# ------------------------------------------------------------------------------------------------ errors
@pytest.mark.parametrize("kind", ["string", "float", "double", "geometry_msgs/Point", "char", ""])
def test_field_rejects_non_primitive_types(kind):
    with pytest.raises(SchemaError):
        Field("x", kind)


def test_field_rejects_negative_count():
    with pytest.raises(SchemaError):
        Field("x", "float64", -1)


@pytest.mark.parametrize("extra", [1, -1, 3])
def test_decode_rejects_partial_messages(extra):
    message = EVERY_PRIMITIVE
    data = message.empty(2).tobytes()
    data = data + b"\0" * extra if extra > 0 else data[:extra]
    with pytest.raises(SchemaError, match="whole number"):
        message.decode(data)


def test_pack_rejects_unknown_columns():
    with pytest.raises(SchemaError, match="no field"):
        EVERY_PRIMITIVE.pack({"f_int8": [1, 2], "nope": [1, 2]})
    with pytest.raises(SchemaError):
        EVERY_PRIMITIVE.encode(f_int8=1, typo=2)


def test_pack_rejects_columns_of_different_lengths():
    with pytest.raises(SchemaError, match="different lengths"):
        EVERY_PRIMITIVE.pack({"f_int8": np.zeros(3, np.int8), "f_float64": np.zeros(4)})
    with pytest.raises(SchemaError, match="different lengths"):
        EVERY_PRIMITIVE.pack({"f_int8": np.zeros(3, np.int8), "a_float32": np.zeros((5, 3))})


def test_pack_rejects_values_of_the_wrong_shape():
    with pytest.raises(SchemaError):
        EVERY_PRIMITIVE.pack({"a_float64": np.zeros((2, 4))})  # 4 values for a float64[3] field
