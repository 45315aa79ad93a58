"""vslab's generic CDR decoder (``acquisition.schemas.dynamic``) against mcap-ros2-support's (the oracle)."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap_ros2._dynamic import serialize_dynamic

from acquisition.schemas.cdr import SchemaError
from acquisition.schemas.dynamic import DynamicMessage

SCHEMA = """\
# a message other tools might write: nested types, strings, sequences, constants, defaults
uint8 MODE_A=1
string NAME = "x"
std_msgs/Header header
string label
float64[] samples
uint8[2] flags
int16[<=4] small
geometry_msgs/Point[] points
geometry_msgs/Point origin
bool ok
string<=8 short_text
int32 count 5
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: geometry_msgs/Point
float64 x
float64 y
float64 z
"""
NAME = "lab_msgs/msg/Sample"

text = st.text(st.characters(codec="utf-8", exclude_characters="\0"), max_size=12)
floats = st.floats(allow_nan=False, width=64)
point = st.fixed_dictionaries({"x": floats, "y": floats, "z": floats})
sample = st.fixed_dictionaries(
    {
        "header": st.fixed_dictionaries(
            {
                "stamp": st.fixed_dictionaries(
                    {"sec": st.integers(0, 2**31 - 1), "nanosec": st.integers(0, 999_999_999)}
                ),
                "frame_id": text,
            }
        ),
        "label": text,
        "samples": st.lists(floats, max_size=6),
        "flags": st.lists(st.integers(0, 255), min_size=2, max_size=2),
        "small": st.lists(st.integers(-(2**15), 2**15 - 1), max_size=4),
        "points": st.lists(point, max_size=3),
        "origin": point,
        "ok": st.booleans(),
        "short_text": st.text(st.characters(codec="ascii", exclude_characters="\0"), max_size=8),
        "count": st.integers(-(2**31), 2**31 - 1),
    }
)


@settings(max_examples=150, deadline=None)
@given(sample)
def test_decodes_what_the_reference_encoder_wrote(value):
    data = serialize_dynamic(NAME, SCHEMA)[NAME](value)
    assert DynamicMessage(NAME, SCHEMA).decode(data) == value


def test_big_endian_and_an_empty_message():
    schema = "int32 a\nfloat64 b\n"
    big = b"\x00\x00\x00\x00" + struct.pack(">i4xd", -7, 2.5)
    assert DynamicMessage("m/A", schema).decode(big) == {"a": -7, "b": 2.5}
    assert DynamicMessage("m/Empty", "# nothing\n").decode(b"\x00\x01\x00\x00\x00") == {}


@pytest.mark.parametrize(
    ("schema", "data", "says"),
    [
        ("float64 a\n", b"\x00\x01\x00\x00\x01\x02", "cut short"),
        ("float64[] a\n", b"\x00\x01\x00\x00\xff\xff\xff\x7f", "longer than the message"),
        ("string s\n", b"\x00\x01\x00\x00\x03\x00\x00\x00\xff\xfe\x00", "not UTF-8"),
        ("int32 a\n", b"\x00\x03\x00\x00\x01\x00\x00\x00", "unsupported CDR encapsulation"),
        ("int32 a\n", b"\x00\x01", "4-byte header"),
    ],
)
def test_damaged_payloads_are_schema_errors(schema, data, says):
    with pytest.raises(SchemaError, match=says):
        DynamicMessage("m/A", schema).decode(data)


@pytest.mark.parametrize(
    ("schema", "says"),
    [
        ("other_msgs/Missing thing\n", "no definition of 'other_msgs/Missing'"),
        ("wstring w\n", "wstring"),
        ("int32\n", "cannot read the definition line"),
        ("in!t32 a\n", "cannot read the type"),
    ],
)
def test_schemas_it_cannot_decode_say_why(schema, says):
    with pytest.raises(SchemaError, match=says):
        DynamicMessage("m/A", schema)
