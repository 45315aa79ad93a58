"""Properties of the Dynamixel Protocol 2.0 codec (and of the emulator fed anything), checked by hypothesis.

Encode/decode round trips for instruction and status packets, however the bytes are split; the CRC's
check vectors and its detection of any corrupted byte; byte stuffing undone exactly and leaving no header
inside a body; and random bytes never making the decoder (nor the emulator) fail with anything but a
returned ``PacketError``. Derandomized and modest (a 2-core machine): the same examples every run.
"""

import struct

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acquisition.codecs import dynamixel as dx
from acquisition.codecs import xm430
from twin.emulators.dynamixel import demo_bus

FAST = settings(
    max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)

ids = st.integers(0, 0xFE)
instructions = st.integers(0, 0xFF).filter(lambda i: i != dx.STATUS)
# parameters rich in the header bytes, so stuffing and false headers are exercised
params = st.lists(st.sampled_from([0x00, 0x01, 0x55, 0xFD, 0xFF]) | st.integers(0, 255), max_size=64).map(
    bytes
)


def _packet(spec: tuple[int, int, bytes]) -> bytes:
    return dx.instruction(*spec)


def _split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in zip([0, *points], [*points, len(data)], strict=True)]


@FAST
@given(ids, instructions, params)
def test_instruction_round_trip(dxl_id, inst, body):
    (packet,) = dx.PacketReader().feed(dx.instruction(dxl_id, inst, body))
    assert packet == dx.Packet(dxl_id, inst, body)


@FAST
@given(ids, st.integers(0, 255), params)
def test_status_round_trip(dxl_id, error, body):
    (packet,) = dx.PacketReader().feed(dx.status(dxl_id, error, body))
    assert packet == dx.Packet(dxl_id, dx.STATUS, body, error)


@FAST
@given(
    st.lists(st.tuples(ids, instructions, params), min_size=1, max_size=5), st.lists(st.integers(0, 10_000))
)
def test_a_stream_splits_into_the_same_packets_however_it_is_cut(packets, cuts):
    stream = b"".join(dx.instruction(*p) for p in packets)
    reader = dx.PacketReader()
    got = [q for chunk in _split(stream, cuts) for q in reader.feed(chunk)]
    assert got == [dx.Packet(*p) for p in packets] and reader.pending() == 0


@FAST
@given(st.binary(max_size=64), st.binary(max_size=64))
def test_crc_continues_across_chunks(a, b):
    assert dx.crc16(a + b) == dx.crc16(b, dx.crc16(a))
    assert dx.crc16(b"123456789") == 0xFEE8


@FAST
@given(ids, instructions, params, st.data())
def test_any_corrupted_byte_is_caught(dxl_id, inst, body, data):
    raw = bytearray(dx.instruction(dxl_id, inst, body))
    k = data.draw(st.integers(0, len(raw) - 1), label="byte")
    raw[k] ^= data.draw(st.integers(1, 255), label="flip")
    assert isinstance(dx.decode(bytes(raw)), dx.PacketError), "header, LEN, body or CRC: never a packet"


@FAST
@given(params)
def test_stuffing_is_undone_exactly_and_hides_every_header(body):
    stuffed = dx.stuff(body)
    assert dx.unstuff(stuffed) == body
    k = stuffed.find(b"\xff\xff\xfd")
    while k >= 0:  # every FF FF FD in a stuffed body is followed by the stuffed FD
        assert stuffed[k + 3 : k + 4] == b"\xfd"
        k = stuffed.find(b"\xff\xff\xfd", k + 4)


@FAST
@given(st.binary(max_size=300))
def test_decode_never_raises(raw):
    assert isinstance(dx.decode(raw), dx.Packet | dx.PacketError)


@FAST
@given(
    st.lists(st.binary(max_size=40) | st.sampled_from([dx.HEADER, dx.HEADER + b"\x01\x03\x00"]), max_size=12)
)
def test_random_bytes_give_packets_or_packet_errors_only(chunks):
    reader = dx.PacketReader()
    for chunk in chunks:
        for item in reader.feed(chunk):
            assert isinstance(item, dx.Packet | dx.PacketError)


@FAST
@given(st.lists(st.binary(max_size=40) | st.tuples(ids, instructions, params).map(_packet), max_size=8))
def test_the_emulator_answers_anything_without_failing(chunks):
    bus = demo_bus()
    for k, chunk in enumerate(chunks):
        reply = bus.feed(chunk, 0.001 * k)
        assert all(isinstance(p, dx.Packet) and p.inst == dx.STATUS for p in dx.PacketReader().feed(reply))


@FAST
@given(st.integers(0, 700), st.binary(min_size=1, max_size=12), st.booleans())
def test_a_write_is_stored_whole_or_not_at_all(address, data, torque):
    bus = demo_bus()
    table = bus.tables[1]
    table.set(dx.TORQUE_ENABLE, int(torque))
    before = bytes(table.data)
    (status,) = dx.PacketReader().feed(
        bus.feed(dx.instruction(1, dx.WRITE, struct.pack("<H", address) + data), 0)
    )
    span = range(address, address + len(data))
    if status.error:
        assert bytes(table.data) == before, f"error {status.error}: nothing stored"
    else:  # every byte of an item landed (unused bytes between items skipped; indirect data plain here)
        assert all(
            table.data[a] == b for a, b in zip(span, data, strict=True) if xm430.item_at(a) is not None
        )
        assert not torque or address >= xm430.EEPROM_END, "EEPROM is locked while the torque is on"
