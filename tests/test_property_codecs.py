"""Properties of three wire codecs, checked by hypothesis: the boards' line protocol
(``acquisition.codecs.board_lines``), the NDI serial API (``acquisition.codecs.ndi``) and the fixed-layout
CDR messages (``acquisition.schemas.cdr``).

Encode/decode round trips; corruption caught; and random bytes never making a decoder fail with anything but
its own error type (a caller catches that one and counts a bad line, it must not die on a stray
UnicodeDecodeError or struct.error). Derandomized and modest (a 2-core machine): the same examples every run.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

from acquisition.codecs import board_lines as bp
from acquisition.codecs import ndi, slcan
from acquisition.errors import CodecError
from acquisition.schemas.cdr import PRIMITIVES, Field, FixedMessage, SchemaError
from twin.emulators.board_firmware import PressureBoardEmulator, StepperBoardEmulator
from twin.emulators.board_hardware import SimplePressureHardware, SimpleStepperHardware

FAST = settings(
    max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
SLOW = settings(FAST, max_examples=40)  # each example builds a decoder (mcap-ros2's oracle)

# ================================================================================== boards' line codec
printable = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=bp.MAX_BODY)
bodies = printable.filter(lambda body: "*" not in body)
u32 = st.integers(0, 2**32 - 1)
tags = st.integers(0, bp.TAG_MODULO - 1)
words = st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E, exclude_characters="*"), min_size=1,
                max_size=9)  # fmt: skip


@FAST
@given(bodies, st.sampled_from([b"\n", b"\r\n", b""]), st.booleans())
def test_board_lines_round_trip(body, end, lowercase):
    line = bp.encode(body)
    assert line.endswith(b"\n") and bp.frame_error(line[:-1]) == 0
    if lowercase:
        line = line[:-3] + line[-3:-1].lower() + b"\n"
    assert bp.decode(line[:-1] + end) == body


@FAST
@given(st.text(max_size=80))
def test_board_encode_refuses_what_a_line_cannot_carry(body):
    raw = body.encode("utf-8")
    carried = len(raw) <= bp.MAX_BODY and all(0x20 <= b <= 0x7E and b != 0x2A for b in raw)
    try:
        line = bp.encode(body)
    except (ValueError, UnicodeEncodeError):
        assert not carried
    else:
        assert carried and bp.decode(line) == body


@FAST
@given(bodies, st.data())
def test_board_checksum_catches_any_changed_byte(body, data):
    line = bp.encode(body)
    at = data.draw(st.integers(0, len(line) - 2), label="at")  # any byte but the final newline
    new = data.draw(st.integers(0, 255).filter(lambda b: b != line[at]), label="byte")
    bad = line[:at] + bytes([new]) + line[at + 1 :]
    try:
        got = bp.decode(bad)
    except bp.BoardChecksumError:
        return
    assert got == body and chr(new).lower() == chr(line[at]).lower(), (
        "only the checksum's letter case may change"
    )


@FAST
@given(st.binary(max_size=90))
def test_board_decode_of_random_bytes_raises_only_its_own_error(data):
    line = data.removesuffix(b"\n")
    try:
        body = bp.decode(data)
    except bp.BoardChecksumError:
        assert bp.frame_error(line) != 0
        return
    line = line.removesuffix(b"\r")
    assert bp.frame_error(line) == 0 and line[:-2] == body.encode("ascii") + b"*"
    assert int(line[-2:], 16) == bp.checksum(line[:-3])


def _message_body(message: bp.Message) -> str:
    """The board's text of a message (what the firmware's snprintf writes)."""
    if isinstance(message, bp.Ok):
        return f"OK {message.tag} {message.verb}"
    if isinstance(message, bp.Err):
        return f"ERR {'-' if message.tag is None else message.tag} {message.code} {message.name}"
    if isinstance(message, bp.Ident):
        return f"ID {message.tag} {message.board} {message.firmware} {message.serial}"
    if isinstance(message, bp.Position):
        return f"POS {message.tag} {message.micros} {message.position_steps} {int(message.moving)}"
    if isinstance(message, bp.Ready):
        return f"READY {message.board} {message.firmware}"
    if isinstance(message, bp.PressureLine):
        m = message
        return f"P {m.seq} {m.micros} {m.counts0} {m.counts1} {m.valves}"
    return f"S {message.seq} {message.micros} {message.position_steps} {int(message.moving)}"


int16 = st.integers(-32768, 32767)
int32 = st.integers(-(2**31), 2**31 - 1)
messages = st.one_of(
    st.builds(bp.Ok, tags, words),
    st.builds(bp.Err, st.none() | tags, st.integers(0, 255), words),
    st.builds(bp.Ident, tags, words, words, words),
    st.builds(bp.Position, tags, u32, int32, st.booleans()),
    st.builds(bp.Ready, words, words),
    st.builds(bp.PressureLine, u32, u32, int16, int16, st.integers(0, 3)),
    st.builds(bp.StepperLine, u32, u32, int32, st.booleans()),
)


@FAST
@given(messages)
def test_board_messages_round_trip(message):
    assert bp.parse_message(bp.decode(bp.encode(_message_body(message)))) == message


@FAST
@given(tags, words, st.lists(words, max_size=3))
def test_board_commands_round_trip(tag, verb, args):
    body = " ".join([str(tag), verb, *args])
    assert bp.parse_command(bp.decode(bp.encode(body))) == bp.Command(tag, verb, tuple(args))


@FAST
@given(printable)
def test_board_parsers_of_random_bodies_raise_only_their_own_error(body):
    for parse in (bp.parse_message, bp.parse_command):
        try:
            parse(body)
        except bp.BoardSyntaxError:
            pass


@FAST
@given(st.sampled_from(["pressure", "stepper"]), st.lists(st.binary(max_size=40), max_size=8))
def test_a_board_emulator_answers_every_line_once_whatever_it_is_fed(which, chunks):
    emu = (PressureBoardEmulator(SimplePressureHardware()) if which == "pressure"
           else StepperBoardEmulator(SimpleStepperHardware()))  # fmt: skip
    emu.poll(0.0)  # READY
    out, lines = b"", 0
    for k, chunk in enumerate(chunks):
        out += emu.feed(chunk, 0.01 * k)
        lines += chunk.count(b"\n")
    replies = out.splitlines(keepends=True)
    assert len(replies) == lines, "exactly one reply per line"
    for reply in replies:
        message = bp.parse_message(bp.decode(reply))  # every reply is a valid line the host can read
        assert not isinstance(message, bp.PressureLine | bp.StepperLine | bp.Ready)


# ============================================================================================ NDI
def test_ndi_crc_check_value_and_documented_commands():
    assert ndi.crc16_arc(b"123456789") == 0xBB3D
    assert ndi.format_command("INIT") == b"INIT:E3A5\r"
    assert ndi.format_command("TX", "0801") == b"TX:0801C19B\r"
    assert ndi.format_reply("OKAY") == b"OKAYA896\r"


names = st.text(st.sampled_from("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"), min_size=1, max_size=8)
params = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=20)


@FAST
@given(names, params)
def test_ndi_commands_round_trip(name, text):
    assert ndi.parse_command(ndi.format_command(name, text)) == (name, text)


@FAST
@given(st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=60))
def test_ndi_replies_round_trip(text):
    assert ndi.parse_reply(ndi.format_reply(text)) == text


@FAST
@given(st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), min_size=1, max_size=40), st.data())
def test_ndi_reply_crc_catches_any_changed_character(text, data):
    reply = ndi.format_reply(text)
    at = data.draw(st.integers(0, len(reply) - 2), label="at")
    new = data.draw(st.integers(0x20, 0x7E).filter(lambda b: chr(b).upper() != chr(reply[at]).upper()))
    try:
        ndi.parse_reply(reply[:at] + bytes([new]) + reply[at + 1 :])
    except (ndi.NdiCrcError, ndi.NdiFormatError):
        return
    raise AssertionError("a changed character went through")


@FAST
@given(st.binary(max_size=60))
def test_ndi_text_parsers_of_random_bytes_raise_only_their_own_errors(data):
    for parse in (ndi.parse_command, ndi.parse_reply):
        try:
            parse(data)
        except (ndi.NdiCrcError, ndi.NdiFormatError):
            pass


@FAST
@given(st.binary(max_size=40))
def test_ndi_reply_with_a_good_crc_over_any_bytes_raises_only_its_own_errors(body):
    """A CRC that matches over non-ASCII bytes (a garbled line whose CRC happens to match, or a device
    sending binary where text was expected) must give NdiFormatError, not UnicodeDecodeError."""
    reply = body + b"%04X\r" % ndi.crc16_arc(body)
    try:
        assert ndi.parse_reply(reply).encode("ascii") == body
    except ndi.NdiFormatError:
        assert not body.isascii()


q_counts = st.integers(-10_000, 10_000)
mm_counts = st.integers(-999_999, 999_999)
handles = st.builds(
    lambda handle, q, t, rms, status, frame, kind: ndi.HandleFrame(
        handle,
        tuple(v / 1e4 for v in q) if kind == "valid" else (math.nan,) * 4,
        tuple(v / 100 for v in t) if kind == "valid" else (math.nan,) * 3,
        rms / 1e4 if kind == "valid" else math.nan,
        status,
        frame,
        kind == "missing",
        kind == "disabled",
    ),
    st.integers(0, 255),
    st.tuples(q_counts, q_counts, q_counts, q_counts),
    st.tuples(mm_counts, mm_counts, mm_counts),
    st.integers(0, 99_999),
    u32,
    u32,
    st.sampled_from(["valid", "missing", "disabled"]),
)


def _same_frames(got: list[ndi.HandleFrame], want: list[ndi.HandleFrame], float32: bool = False) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert (g.handle, g.missing, g.disabled) == (w.handle, w.missing, w.disabled)
        if not w.disabled:
            assert (g.port_status, g.frame) == (w.port_status, w.frame)
        wanted = [*w.quaternion, *w.position_mm, w.rms_error]
        if w.missing or w.disabled:
            assert all(math.isnan(v) for v in [*g.quaternion, *g.position_mm, g.rms_error])
        else:
            if float32:
                wanted = np.float32(wanted).tolist()
            assert [*g.quaternion, *g.position_mm, g.rms_error] == wanted


@FAST
@given(st.lists(handles, max_size=4), st.integers(0, 0xFFFF))
def test_ndi_tx_round_trip(frames, system_status):
    text = ndi.format_tx(frames, system_status)
    _same_frames(ndi.parse_tx(text), frames)
    assert ndi.parse_tx_system_status(text) == system_status
    assert ndi.parse_reply(ndi.format_reply(text)) == text


@FAST
@given(st.lists(handles, max_size=4), st.integers(0, 0xFFFF))
def test_ndi_bx_round_trip(frames, system_status):
    data = ndi.format_bx(frames, system_status)
    assert ndi.bx_total_length(data[:6]) == len(data)
    _same_frames(ndi.parse_bx(data), frames, float32=True)


@FAST
@given(st.text(max_size=120))
def test_ndi_tx_parser_of_random_text_raises_only_its_own_error(text):
    for parse in (ndi.parse_tx, ndi.parse_tx_system_status):
        try:
            parse(text)
        except ndi.NdiFormatError:
            pass


@FAST
@given(st.lists(handles, min_size=1, max_size=3), st.data())
def test_ndi_tx_parser_of_a_damaged_frame_raises_only_its_own_error(frames, data):
    """A real TX text with one character replaced by any character (digits of other scripts included)."""
    text = ndi.format_tx(frames)
    at = data.draw(st.integers(0, len(text) - 1), label="at")
    char = data.draw(st.characters(exclude_categories=["Cs"]) | st.sampled_from("²٣-+ "), label="char")
    for parse in (ndi.parse_tx, ndi.parse_tx_system_status):
        try:
            parse(text[:at] + char + text[at + 1 :])
        except ndi.NdiFormatError:
            pass


@FAST
@given(st.binary(max_size=80), st.booleans())
def test_ndi_bx_parser_of_random_bytes_raises_only_its_own_errors(body, framed):
    """Raw bytes, and random bodies behind a correct header and CRCs (to reach the body parser)."""
    data = body
    if framed:
        head = ndi.BX_START + struct.pack("<H", len(body))
        data = head + struct.pack("<H", ndi.crc16_arc(head)) + body + struct.pack("<H", ndi.crc16_arc(body))
    for parse in (ndi.parse_bx, ndi.bx_total_length):
        try:
            parse(data)
        except (ndi.NdiCrcError, ndi.NdiFormatError):
            pass


# ============================================================================================ CDR
field_lists = st.lists(st.tuples(st.sampled_from(sorted(PRIMITIVES)), st.integers(0, 3)), min_size=1,
                       max_size=6)  # fmt: skip


def _message(spec: list[tuple[str, int]]) -> FixedMessage:
    return FixedMessage("lab_msgs/msg/Random", tuple(Field(f"f{i}", t, n) for i, (t, n) in enumerate(spec)))


def _values(message: FixedMessage, seed: int) -> dict[str, np.ndarray]:
    """Random values for every field, over each type's whole range (NaN and ±inf for floats)."""
    rng = np.random.default_rng(seed)
    values = {}
    for f in message.fields:
        dtype = np.dtype(PRIMITIVES[f.type])
        raw = rng.integers(0, 256, dtype=np.uint8, size=dtype.itemsize * max(f.count, 1))
        value = raw.view(dtype) if f.type != "bool" else raw % 2 == 1
        if dtype.kind == "f":  # one NaN (a signalling NaN's bits do not survive a trip through a double)
            value = np.where(np.isnan(value), np.array(np.nan, dtype), value).astype(dtype)
        values[f.name] = value if f.count else value[0]
    return values


@FAST
@given(field_lists, st.integers(0, 2**32 - 1), st.integers(1, 5))
def test_cdr_rows_round_trip_and_the_layout_is_aligned(spec, seed, n):
    message = _message(spec)
    columns = {name: np.array([_values(message, seed + k)[name] for k in range(n)]) for name in
               _values(message, seed)}  # fmt: skip
    rows = message.pack(columns)
    data = message.canonical_bytes(rows).tobytes()
    assert len(data) == n * message.size
    back = message.decode(data)
    for name, column in columns.items():
        np.testing.assert_array_equal(back[name], column)
        assert np.ascontiguousarray(back[name]).tobytes() == np.ascontiguousarray(column).tobytes()
    assert bytes(back["_cdr_header"][0]) == b"\x00\x01\x00\x00"
    for f in message.fields:  # each field aligned to its own size, counted from the end of the header
        offset = message.dtype.fields[f.name][1] - 4
        assert offset % np.dtype(PRIMITIVES[f.type]).itemsize == 0


@SLOW
@given(field_lists, st.integers(0, 2**32 - 1))
def test_cdr_bytes_are_mcap_ros2s_bytes(spec, seed):
    """The oracle: mcap-ros2-support serialises the same values to the same bytes and reads ours back."""
    message = _message(spec)
    values = _values(message, seed)
    data = message.encode(**values)
    plain = {name: np.asarray(v).tolist() for name, v in values.items()}
    assert serialize_dynamic(message.name, message.ros2msg)[message.name](plain) == data
    decoded = generate_dynamic(message.name, message.ros2msg)[message.name](data)
    for name, value in plain.items():
        got = getattr(decoded, name)
        got = list(got) if isinstance(got, bytes | bytearray) else got
        dtype = PRIMITIVES[message.fields[int(name[1:])].type]
        assert np.array(got, dtype=dtype).tobytes() == np.array(value, dtype=dtype).tobytes()


@FAST
@given(field_lists, st.binary(max_size=200))
def test_cdr_decode_of_random_bytes_raises_only_its_own_error(spec, data):
    message = _message(spec)
    try:
        rows = message.decode(data)
    except SchemaError:
        assert len(data) % message.size
        return
    assert len(rows) * message.size == len(data)


def _garbled(crc: bytes, into: str) -> bytes:
    """``crc`` (4 hex digits, the first a 0) with a space or sign over that 0, or an underscore between."""
    return crc[:2] + b"_" + crc[3:] if into == "_" else into.encode() + crc[1:]


def _leading_zero(prefix: bytes) -> bytes:
    """A text after ``prefix`` whose CRC starts with the digit 0."""
    return next(t for i in range(1000) if ndi._hex_crc(prefix + (t := f"{i:04d}".encode())).startswith(b"0"))


@pytest.mark.parametrize("into", [" ", "+", "-", "_"])
def test_a_crc_field_is_four_hex_digits_exactly(into):
    """int(x, 16) takes " ABC", "+ABC", "-0BC" and "A_BC": a reply or command whose CRC starts with 0 went
    through with that digit garbled into a space or a sign (found by the property test above)."""
    reply = b"A_" + _leading_zero(b"A_")
    assert ndi.parse_reply(reply + ndi._hex_crc(reply) + b"\r") == reply.decode()
    with pytest.raises(ndi.NdiFormatError):
        ndi.parse_reply(reply + _garbled(ndi._hex_crc(reply), into) + b"\r")
    params = _leading_zero(b"TX:")
    assert ndi.parse_command(b"TX:" + params + ndi._hex_crc(b"TX:" + params)) == ("TX", params.decode())
    with pytest.raises(ndi.NdiFormatError):
        ndi.parse_command(b"TX:" + params + _garbled(ndi._hex_crc(b"TX:" + params), into))


@pytest.mark.parametrize("line", [b"t 2381122", b"t+2381122", b"t1_381122", b"T 00001232AABB", b"t1239AA"])
def test_an_slcan_identifier_or_length_with_a_foreign_character_is_malformed(line):
    assert slcan.parse_frame(b"t1232AABB").can_id == 0x123  # a whole line
    with pytest.raises(CodecError):
        slcan.parse_frame(line)
