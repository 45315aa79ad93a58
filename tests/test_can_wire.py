"""POPUP's CAN wire, below the drivers: frame lengths on the bus, the slcan codec, the bus's arbitration and
counters, the slcan adapter's replies, and the CiA 402 drive emulator's state machine, SDO aborts and faults,
each driven with raw frames (the driver-level tests, with python-can and canopen, are test_can_drives.py)."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from acquisition.codecs import slcan
from acquisition.codecs.can import CanFrame, frame_bits, stuff_bits, unstuffed_bits
from acquisition.errors import CodecError
from models.robot import CAN_DIR
from twin.can_bus import CanBus, CanNode
from twin.emulators import cia402_drive as D
from twin.emulators.canopen_node import ABORT_NO_OBJECT, ABORT_READ_ONLY, ABORT_STATE
from twin.emulators.slcan_adapter import SlcanAdapter

EDS = CAN_DIR / "popup_drive.eds"
frames = st.builds(
    lambda ext, ident, data: CanFrame(ident & (0x1FFFFFFF if ext else 0x7FF), data, ext),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
    st.binary(max_size=8),
)


# ------------------------------------------------------------------------------------------ frames
def test_stuff_bits_follow_the_five_equal_bits_rule():
    assert stuff_bits([0] * 5) == 1
    assert stuff_bits([0] * 10) == 2  # the stuff bit starts the next run
    assert stuff_bits([0, 1] * 20) == 0
    assert stuff_bits([1] * 4 + [0] * 4) == 0


@given(st.integers(0, 0x7FF), st.binary(min_size=8, max_size=8))
def test_an_8_byte_standard_frame_takes_111_to_135_bits(ident, data):
    """111 bits with the 3-bit interframe space, plus at most 24 stuff bits (Davis et al. 2007)."""
    assert 111 <= frame_bits(CanFrame(ident, data)) <= 135


def test_frame_lengths_count_identifier_and_data_bits():
    empty = CanFrame(0x555, b"")  # alternating bits: no stuffing in the identifier
    assert len(unstuffed_bits(empty)) == 1 + 11 + 3 + 4 + 15
    assert len(unstuffed_bits(CanFrame(0x555, b"", extended=True))) == 1 + 11 + 2 + 18 + 3 + 4 + 15
    assert frame_bits(CanFrame(0x80, b"")) >= 47  # a SYNC


@pytest.mark.parametrize("bad", [dict(can_id=0x800), dict(can_id=-1), dict(can_id=1, data=b"123456789")])
def test_impossible_frames_are_refused(bad):
    with pytest.raises(CodecError):
        CanFrame(**bad)


# ------------------------------------------------------------------------------------------- slcan
@given(frames)
def test_slcan_lines_round_trip(frame):
    line = slcan.encode_frame(frame)
    assert line.endswith(b"\r")
    assert slcan.parse_frame(line[:-1]) == frame


def test_slcan_lines_match_python_can_s_format():
    assert slcan.encode_frame(CanFrame(0x123, bytes([0xDE, 0xAD]))) == b"t1232DEAD\r"
    assert slcan.encode_frame(CanFrame(0x1ABCDEF, b"\x01", extended=True)) == b"T01ABCDEF101\r"
    assert slcan.parse_frame(b"t12320102ABCD") == CanFrame(0x123, b"\x01\x02")  # a trailing stamp is ignored


@pytest.mark.parametrize("line", [b"x123", b"t12", b"t1239", b"t123201", b"tXYZ0", b"t1232ZZZZ"])
def test_malformed_slcan_lines_are_refused(line):
    with pytest.raises(CodecError):
        slcan.parse_frame(line)


# --------------------------------------------------------------------------------------------- bus
class Talker(CanNode):
    def __init__(self) -> None:
        self.heard: list[tuple[float, CanFrame]] = []

    def receive(self, frame, t):
        self.heard.append((t, frame))
        return []


def test_the_lowest_identifier_wins_arbitration_and_frames_take_their_bit_time():
    a, b, listener = Talker(), Talker(), Talker()
    bus = CanBus(1_000_000, [a, b, listener])
    high, low = CanFrame(0x300, b"\x01" * 8), CanFrame(0x100, b"\x02" * 8)
    bus.offer(a, 0.0, high)
    bus.offer(b, 0.0, low)
    bus.run_until(1.0)
    (t1, f1), (t2, f2) = listener.heard
    assert (f1, f2) == (low, high)
    assert t1 == pytest.approx(frame_bits(low) * 1e-6) and t2 == pytest.approx(t1 + frame_bits(high) * 1e-6)
    assert [f for _, f in a.heard] == [low] and [f for _, f in b.heard] == [high]  # not their own
    c = bus.counters
    assert (
        c.frames == 2
        and c.bits == frame_bits(low) + frame_bits(high)
        and c.busy_s == pytest.approx(c.bits * 1e-6)
    )


def test_a_frame_is_delivered_only_once_its_last_bit_is_sent():
    a, listener = Talker(), Talker()
    bus = CanBus(125_000, [a, listener])
    bus.offer(a, 0.0, CanFrame(0x10, b"\0" * 8))
    bus.run_until(0.5e-3)
    assert listener.heard == []
    assert bus.next_event_s() == pytest.approx(frame_bits(CanFrame(0x10, b"\0" * 8)) / 125_000)


def test_a_bus_off_carries_nothing_and_counts_what_it_lost():
    a, listener = Talker(), Talker()
    bus = CanBus(1_000_000, [a, listener])
    bus.set_bus_off(True)
    bus.offer(a, 0.0, CanFrame(0x10, b"\0"))
    bus.run_until(1.0)
    assert listener.heard == [] and bus.counters.lost == 1


# ----------------------------------------------------------------------------------------- adapter
def test_the_adapter_answers_as_a_lawicel_adapter_does():
    bus = CanBus(1_000_000)
    listener = Talker()
    bus.attach(listener)
    adapter = SlcanAdapter(bus)
    assert adapter.feed(b"t1230\r", 0.0) == slcan.BEL  # closed
    assert adapter.feed(b"O\r", 0.0) == slcan.BEL  # no bit rate yet
    assert adapter.feed(b"S8\r\rO\r", 0.0) == b"\r\r\r"  # python-can's init: S8, empty data rate, open
    assert adapter.feed(b"S6\r", 0.0) == slcan.BEL  # not while open
    assert adapter.feed(b"t1232ABCD\r", 0.0) == b"z\r"
    assert adapter.feed(b"V\r", 0.0).startswith(b"V")
    adapter.poll(1.0)
    assert [f for _, f in listener.heard] == [CanFrame(0x123, b"\xab\xcd")]
    bus.offer(listener, 1.0, CanFrame(0x181, b"\x01"))
    assert adapter.poll(2.0) == b"t181101\r"


def test_an_adapter_at_the_wrong_bit_rate_passes_nothing():
    bus = CanBus(1_000_000)
    listener = Talker()
    bus.attach(listener)
    adapter = SlcanAdapter(bus)
    assert adapter.feed(b"S6\rO\r", 0.0) == b"\r\r"  # 500 kbit/s on a 1 Mbit/s bus
    assert adapter.feed(b"t1230\r", 0.0) == slcan.BEL
    bus.offer(listener, 0.0, CanFrame(0x181, b"\x01"))
    assert adapter.poll(1.0) == b""


# ----------------------------------------------------------------------------------------- drive
class Joint:
    """A joint that is wherever it was last sent (an ideal position loop), or a lagging one."""

    def __init__(self, lag: bool = False) -> None:
        self.position, self.goal, self.lag = 0.1, 0.1, lag

    def sense(self, t):
        return self.position, 0.0, 12.0

    def command(self, goal, velocity, acceleration, t):
        self.goal, self.velocity = goal, velocity
        if not self.lag:
            self.position = goal

    def hold(self, t):
        self.goal = self.position


def _sdo(drive, data: bytes, t: float = 1.0) -> bytes:
    ((_, frame),) = drive.receive(CanFrame(0x600 + drive.node_id, data), t)
    assert frame.can_id == 0x580 + drive.node_id
    return frame.data


def _write(drive, index: int, value: int, size: int, sub: int = 0) -> bytes:
    cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    return _sdo(
        drive,
        struct.pack("<BHB", cmd, index, sub)
        + value.to_bytes(size, "little", signed=value < 0).ljust(4, b"\0"),
    )


def _read(drive, index: int, sub: int = 0) -> int:
    reply = _sdo(drive, struct.pack("<BHB4x", 0x40, index, sub))
    assert reply[0] & 0xE0 == 0x40, f"aborted: {reply.hex()}"
    return int.from_bytes(reply[4:], "little")


def _booted(joint: Joint) -> D.Cia402Drive:
    drive = D.Cia402Drive(5, EDS, joint)
    (_t, boot), *_ = drive.produce(0.0)
    assert boot == CanFrame(0x705, b"\x00")  # boot-up, then pre-operational
    return drive


def _abort_code(reply: bytes) -> int:
    assert reply[0] == 0x80
    return struct.unpack_from("<I", reply, 4)[0]


def test_the_drive_walks_the_cia402_states_and_shows_them_in_its_statusword():
    drive = _booted(Joint())
    assert _read(drive, D.STATUSWORD) & 0x4F == D.State.SWITCH_ON_DISABLED
    assert _write(drive, D.MODE, 8, 1)[0] == 0x60 and _read(drive, D.MODE_DISPLAY) == 8
    for cw, state in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
        _write(drive, D.CONTROLWORD, cw, 2)
        assert _read(drive, D.STATUSWORD) & 0x6F == state
    _write(drive, D.CONTROLWORD, 0x02, 2)  # quick stop, option code 2: then switch on disabled
    assert _read(drive, D.STATUSWORD) & 0x4F == D.State.SWITCH_ON_DISABLED


def test_a_target_beyond_the_software_limits_is_clamped_and_flagged():
    joint = Joint()
    drive = _booted(joint)
    _write(drive, D.MODE, 8, 1)
    for cw in (0x06, 0x07, 0x0F):
        _write(drive, D.CONTROLWORD, cw, 2)
    high = drive.get(D.SOFTWARE_LIMITS, 2)
    _write(drive, D.TARGET_POSITION, high + 50_000, 4)
    assert joint.goal == pytest.approx(high / drive.counts_per_rad)
    assert _read(drive, D.STATUSWORD) & D.SW_LIMIT


def test_csp_set_points_are_interpolated_over_the_interpolation_period():
    """A drive's fine interpolator: from one set-point to the next in a straight line over 0x60C2 (value ×
    10^index s, INTEGER8 index), not a jump the position loop takes at full speed."""
    joint = Joint()
    drive = _booted(joint)
    _write(drive, D.MODE, 8, 1)
    assert _write(drive, D.INTERPOLATION_PERIOD, 100, 1, sub=1)[0] == 0x60
    assert _write(drive, D.INTERPOLATION_PERIOD, -4, 1, sub=2)[0] == 0x60
    assert drive.interpolation_period_s == pytest.approx(0.01)
    for cw in (0x06, 0x07, 0x0F):
        _write(drive, D.CONTROLWORD, cw, 2)
    here = round(0.1 * drive.counts_per_rad)
    _write(drive, D.TARGET_POSITION, here + 65, 4)  # 65 counts in 10 ms
    assert joint.velocity * drive.counts_per_rad == pytest.approx(6500)
    _write(drive, D.TARGET_POSITION, here + 65, 4)  # the same set-point: hold it, gently
    assert joint.velocity * drive.counts_per_rad == pytest.approx(100)


def test_a_following_error_faults_the_drive_with_an_emcy_and_a_reset_clears_it():
    joint = Joint(lag=True)
    drive = _booted(joint)
    _write(drive, D.MODE, 8, 1)
    for cw in (0x06, 0x07, 0x0F):
        _write(drive, D.CONTROLWORD, cw, 2)
    _write(drive, D.TARGET_POSITION, round((0.1 + 0.5) * drive.counts_per_rad), 4)  # 0.5 rad > the window
    assert _read(drive, D.STATUSWORD) & 0x4F == D.State.FAULT
    assert _read(drive, D.ERROR_CODE) == D.FOLLOWING_ERROR and _read(drive, D.ERROR_REGISTER) == 0x21
    (_, emcy), *_ = drive.produce(1.0)
    assert emcy.can_id == 0x85 and emcy.data[:3] == bytes([0x11, 0x86, 0x21])
    assert joint.goal == joint.position  # the brake holds
    _write(drive, D.CONTROLWORD, 0x80, 2)  # fault reset: rising edge of bit 7
    assert _read(drive, D.STATUSWORD) & 0x4F == D.State.SWITCH_ON_DISABLED
    (_, cleared), *_ = drive.produce(1.0)
    assert cleared.data[:2] == b"\0\0"


def test_the_drive_refuses_sdo_requests_with_the_standard_abort_codes():
    drive = _booted(Joint())
    assert _abort_code(_write(drive, D.STATUSWORD, 1, 2)) == ABORT_READ_ONLY
    assert _abort_code(_sdo(drive, struct.pack("<BHB4x", 0x40, 0x5FFF, 0))) == ABORT_NO_OBJECT
    assert _abort_code(_write(drive, 0x1A00, 0x60640020, 4, sub=1)) == ABORT_STATE  # PDO enabled, count ≠ 0


def test_a_stopped_node_answers_no_sdo_and_heartbeats_its_state():
    drive = _booted(Joint())
    _write(drive, 0x1017, 100, 2)
    assert drive.receive(CanFrame(0x000, bytes([0x02, 5])), 1.0) == []  # NMT stop
    assert drive.receive(CanFrame(0x605, bytes([0x40, 0, 0x10, 0, 0, 0, 0, 0])), 1.1) == []
    beats = [f for _, f in drive.produce(1.3)]
    assert beats and all(f == CanFrame(0x705, b"\x04") for f in beats)
