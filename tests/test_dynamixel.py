"""Dynamixel Protocol 2.0: codec check vectors, the bus emulator byte for byte, the real SDK against it."""

import struct
import time

import numpy as np
import pytest
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler, PortHandler

from acquisition.codecs import dynamixel as dx
from acquisition.devices.servo_bus import ServoBus
from acquisition.errors import DeviceDisconnectedError, DeviceNotFoundError, DeviceProtocolError
from twin.emulators.dynamixel import demo_bus
from twin.ptyhost import send_control

DEMO = "servo_bus=twin.emulators.dynamixel:demo_bus"


# ------------------------------------------------------------------------------------------- codec
def test_crc_check_vectors():
    assert dx.crc16(b"123456789") == 0xFEE8  # CRC-16/BUYPASS
    assert dx.instruction(1, dx.PING) == bytes.fromhex("FFFFFD00010300 01 194E".replace(" ", ""))


def test_stuffing_round_trip_and_length_after_stuffing():
    params = b"\x74\x00\xff\xff\xfd\x01"
    packet = dx.instruction(1, dx.WRITE, params)
    body = packet[7:-2]
    assert body == b"\x03" + dx.stuff(params) and b"\xff\xff\xfd\xfd" in body
    assert struct.unpack_from("<H", packet, 5)[0] == len(body) + 2
    (decoded,) = dx.PacketReader().feed(packet)
    assert decoded.params == params


def test_reader_splits_by_length_not_by_headers_in_params():
    # the SDK sends WRITE params unstuffed (its known bug): a header inside params must not split the packet
    params = b"\x74\x00" + dx.HEADER + b"\x01"
    head = dx.HEADER + b"\x01" + struct.pack("<H", len(params) + 3)
    body = bytes([dx.WRITE]) + params
    raw = head + body + struct.pack("<H", dx.crc16(head + body))
    reader = dx.PacketReader()
    assert reader.feed(raw[:5]) == []
    packets = reader.feed(raw[5:] + dx.instruction(2, dx.PING))
    assert [p.inst for p in packets] == [dx.WRITE, dx.PING]


def test_corrupted_packet_is_flagged():
    raw = bytearray(dx.instruction(1, dx.PING))
    raw[-1] ^= 0xFF
    (bad,) = dx.PacketReader().feed(bytes(raw))
    assert isinstance(bad, dx.CrcError) and isinstance(bad, dx.PacketError)
    assert isinstance(dx.decode(dx.HEADER + b"\x01\x00\x00"), dx.PacketError), "LEN 0: not a packet"


def test_emulator_drops_a_packet_cut_short():
    """A packet whose rest never comes (a corrupted LEN) is dropped after the servo's packet timeout."""
    bus = demo_bus()
    assert bus.feed(dx.HEADER + b"\x01\xff\x00\x02", 0.0) == b"", "waits for 255 more bytes"
    (pong,) = _status(bus.feed(dx.instruction(1, dx.PING), 1.0))
    assert pong.dxl_id == 1 and pong.error == 0


# ---------------------------------------------------------------------------------------- emulator
def _status(reply: bytes) -> list[dx.Packet]:
    return dx.PacketReader().feed(reply)


def test_emulator_ping_read_write_and_errors():
    bus = demo_bus()
    (pong,) = _status(bus.feed(dx.instruction(1, dx.PING), 0.0))
    assert pong.inst == dx.STATUS and struct.unpack("<HB", pong.params)[0] == dx.XM430_W350_MODEL
    assert bus.feed(dx.instruction(7, dx.PING), 0.0) == b"", "an absent servo stays silent"
    assert len(_status(bus.feed(dx.instruction(dx.BROADCAST_ID, dx.PING), 0.0))) == 2
    (ok,) = _status(bus.feed(dx.instruction(1, dx.WRITE, struct.pack("<HB", 64, 1)), 0.0))
    assert ok.error == 0
    (denied,) = _status(bus.feed(dx.instruction(1, dx.WRITE, struct.pack("<HB", 11, 1)), 0.0))
    assert denied.error == dx.ERR_ACCESS, "EEPROM is read-only with torque on"
    (bad,) = _status(bus.feed(dx.instruction(1, dx.READ, struct.pack("<HH", 655, 10)), 0.0))
    assert bad.error == dx.ERR_ACCESS and bad.params == bytes(10), "past address 661: zeros, Access Error"
    (gap,) = _status(bus.feed(dx.instruction(1, dx.READ, struct.pack("<HH", 250, 10)), 0.0))
    assert gap.error == 0 and len(gap.params) == 10, "unused addresses read as zeros"
    (unknown,) = _status(bus.feed(dx.instruction(1, 0x77), 0.0))
    assert unknown.error == dx.ERR_INSTRUCTION
    assert bus.feed(dx.instruction(dx.BROADCAST_ID, 0x77), 0.0) == b"", "no status to a broadcast"
    assert bus.feed(dx.instruction(dx.BROADCAST_ID, dx.WRITE, struct.pack("<HB", 65, 1)), 0.0) == b""


def test_emulator_sync_read_answers_in_the_order_asked_and_fast_sync_read():
    bus = demo_bus()
    replies = _status(
        bus.feed(dx.instruction(dx.BROADCAST_ID, dx.SYNC_READ, struct.pack("<HH", 132, 4) + b"\x02\x01"), 0)
    )
    assert [p.dxl_id for p in replies] == [2, 1]
    fast = bus.feed(
        dx.instruction(dx.BROADCAST_ID, dx.FAST_SYNC_READ, struct.pack("<HH", 132, 4) + b"\x01\x02"), 0
    )
    (packet,) = _status(fast)
    # per servo: error, id, 4 data bytes, running CRC; the decoder has consumed the first error byte
    assert packet.dxl_id == dx.BROADCAST_ID and len(packet.params) == 2 * (1 + 1 + 4 + 2) - 1
    assert packet.params[0] == 1 and packet.params[8] == 2
    bulk = _status(
        bus.feed(dx.instruction(dx.BROADCAST_ID, dx.BULK_READ, struct.pack("<BHHBHH", 2, 0, 2, 1, 132, 4)), 0)
    )
    assert [(p.dxl_id, len(p.params)) for p in bulk] == [(2, 2), (1, 4)]


# ------------------------------------------------------------------------------ the real SDK, a pty
def test_real_sdk_sync_write_reaches_goals_and_sync_read_reads_them(host_factory):
    with host_factory(DEMO) as ports:
        port, packet = PortHandler(ports["servo_bus"]), PacketHandler(2.0)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            for i in (1, 2):
                assert packet.write1ByteTxRx(port, i, 64, 1)[0] == COMM_SUCCESS
            writer = GroupSyncWrite(port, packet, 116, 4)
            for i, goal in ((1, 2100), (2, 1900)):
                writer.addParam(i, goal.to_bytes(4, "little"))
            assert writer.txPacket() == COMM_SUCCESS
            reader = GroupSyncRead(port, packet, 132, 4)
            for i in (1, 2):
                reader.addParam(i)
            deadline = time.monotonic() + 3.0  # wall time: a loaded machine reads slower
            while time.monotonic() < deadline:
                assert reader.txRxPacket() == COMM_SUCCESS
                positions = [reader.getData(i, 132, 4) for i in (1, 2)]
                if positions == [2100, 1900]:
                    break
            assert positions == [2100, 1900]
            assert reader.fastSyncRead() == COMM_SUCCESS
            assert [reader.getData(i, 132, 4) for i in (1, 2)] == [2100, 1900]
        finally:
            port.closePort()


def test_servo_bus_driver_commands_and_reads_si(host_factory):
    with host_factory(DEMO) as ports, ServoBus(ports["servo_bus"], ids=[1, 2]) as bus:
        assert bus.models == {1: dx.XM430_W350_MODEL, 2: dx.XM430_W350_MODEL}
        bus.configure(profile_velocity_rad_s=0.0, p_gain=850, d_gain=10)
        port, packet = bus._port, bus._packet
        assert packet.read2ByteTxRx(port, 1, 84)[0] == 850 and packet.read2ByteTxRx(port, 2, 80)[0] == 10
        assert packet.read1ByteTxRx(port, 1, 11)[0] == 3, "position control mode"
        bus.set_torque(True)
        goal = np.deg2rad([10.0, -20.0])
        bus.write_goals(goal)
        deadline = time.monotonic() + 3.0  # wall time, not a count of reads: a loaded machine reads slower
        while time.monotonic() < deadline:
            state = bus.read_state()
            if np.allclose(state.position_rad, goal, atol=np.pi / 2048):
                break
        np.testing.assert_allclose(state.position_rad, goal, atol=np.pi / 2048)
        assert state.host_ns > 0 and state.tick_ms.shape == (2,)


def test_missing_servo_is_a_clear_error(host_factory):
    with host_factory(DEMO) as ports, pytest.raises(DeviceNotFoundError, match="servo ID 5 does not answer"):
        ServoBus(ports["servo_bus"], ids=[1, 5], retries=0).open()


def test_no_such_port_is_a_clear_error(tmp_path):
    with pytest.raises(DeviceNotFoundError, match="nothing-here"):
        ServoBus(str(tmp_path / "nothing-here"), ids=[1]).open()


def test_corrupted_or_dropped_replies_are_retried_then_reported(host_factory, tmp_path):
    run = tmp_path / "run"
    with host_factory(DEMO) as ports, ServoBus(ports["servo_bus"], ids=[1, 2], retries=2) as bus:
        send_control(run, {"op": "fault", "device": "servo_bus", "kind": "corrupt", "count": 1})
        assert bus.read_state().position_counts.shape == (2,), "one corrupted reply: the retry succeeds"
        send_control(run, {"op": "fault", "device": "servo_bus", "kind": "drop", "count": 2})
        assert bus.read_state().position_counts.shape == (2,), "two dropped replies: the third try succeeds"
        send_control(run, {"op": "fault", "device": "servo_bus", "kind": "corrupt", "count": 10})
        with pytest.raises(DeviceProtocolError, match=r"sync read.*after 3 attempts"):
            bus.read_state()


def test_unplugged_bus_is_reported_and_reconnects(host_factory, tmp_path):
    run = tmp_path / "run"
    with host_factory(DEMO) as ports, ServoBus(ports["servo_bus"], ids=[1, 2], retries=1) as bus:
        bus.read_state()
        send_control(run, {"op": "fault", "device": "servo_bus", "kind": "unplug"})
        with pytest.raises((DeviceDisconnectedError, DeviceProtocolError)):
            bus.read_state()
        with pytest.raises(DeviceNotFoundError):
            bus.reconnect()
        send_control(run, {"op": "fault", "device": "servo_bus", "kind": "plug"})
        bus.reconnect()
        assert bus.read_state().position_counts.shape == (2,)
