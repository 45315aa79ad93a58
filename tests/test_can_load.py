"""POPUP's CAN bus at its bit rate: a frame's exact bits against the worst-case bound, the load the robot
description's rates put on the bus (computed), the load the twin's bus measures when POPUP's devices run on
it, and a bus offered more than it carries: frames delayed, lost, counted, and shown by the adapter's
Lawicel status flags. Everything runs in simulated time (the rig's own objects, no pty, no clock): exact
and fast on a busy machine. The same stack in real time, with python-can and canopen, is test_can_drives.py
and test_can_boards.py."""

from __future__ import annotations

import struct

import canopen
import pytest
from hypothesis import given
from hypothesis import strategies as st

from acquisition.codecs import slcan
from acquisition.codecs.can import CanFrame, crc15, stuff_bits
from acquisition.devices.bus_budget import can_frame_bits, can_frame_exact_bits
from acquisition.devices.can_budget import popup_can_load
from acquisition.devices.popup_boards import BoardFrames
from models.robot import load_robot
from twin.can_bus import CanBus, CanNode
from twin.emulators import slcan_adapter as A
from twin.rig import Rig

frames = st.builds(
    lambda ext, ident, data: CanFrame(ident & (0x1FFFFFFF if ext else 0x7FF), data, ext),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
    st.binary(max_size=8),
)


# ------------------------------------------------------------------------------------- frame bits
@given(frames)
def test_a_frames_exact_bits_never_exceed_the_worst_case(frame):
    exact = can_frame_exact_bits(frame)
    assert can_frame_bits(len(frame.data), frame.extended, worst_case=False) <= exact
    assert exact <= can_frame_bits(len(frame.data), frame.extended)


def test_the_crc_is_can_s_crc15_by_its_catalogued_check_value():
    """The CRC RevEng catalogue's CRC-15/CAN (poly 0x4599, init 0, no reflection, no xor): check 0x059E,
    the CRC of the ASCII bytes "123456789"."""
    bits = [(byte >> (7 - k)) & 1 for byte in b"123456789" for k in range(8)]
    assert crc15(bits) == 0x059E


@pytest.mark.parametrize("n", range(9))
def test_the_worst_case_is_the_stuffing_rule_on_the_most_stuffing_bits(n):
    """Five equal bits, then groups of four, each the complement of the one before: the stuff bit after a
    group starts the next run, so every four bits cost one more: ⌊(34 + 8n − 1)/4⌋ stuff bits."""
    bits = [0] * 5
    while len(bits) < 34 + 8 * n:
        bits += [1 - bits[-1]] * 4
    bits = bits[: 34 + 8 * n]
    assert 47 + 8 * n + stuff_bits(bits) == can_frame_bits(n)


def test_no_real_frame_without_data_reaches_the_bound():
    """The bound needs that pattern through IDE and r0 (always dominant) and the CRC: over all 2,048
    identifiers a frame without data takes at most 53 bits (of the bound's 55); all zeros stuff every five."""
    exact = [can_frame_exact_bits(CanFrame(ident, b"")) for ident in range(0x800)]
    assert max(exact) == 53 < can_frame_bits(0)
    assert can_frame_exact_bits(CanFrame(0, b"")) == 47 + 34 // 5  # 34 zeros under stuffing: 6 stuff bits


# ------------------------------------------------------------------------------ computed load
def test_popups_configured_rates_load_its_bus_by_the_frames_of_its_eds_and_dbc():
    robot = load_robot("popup")
    load = popup_can_load(robot)
    rows = {r["frame"]: r for r in load["rows"]}
    assert load["bitrate"] == 1_000_000 and load["sync_hz"] == robot.devices["can_bus"].rate_hz
    # the drive's EDS: statusword 16 + position 32 bits, velocity 32 + torque 16, target position 32
    assert (rows["TPDO1"]["bytes"], rows["TPDO2"]["bytes"], rows["RPDO2"]["bytes"]) == (6, 6, 4)
    assert rows["TPDO1"]["can_ids"] == [0x181, 0x182, 0x183] and rows["TPDO1"]["frames_per_s"] == 300
    assert rows["Link2Accel"]["frames_per_s"] == 1000 and "Link1Accel" not in rows  # the tip IMU's ODR
    assert rows["MainPressure"]["frames_per_s"] == 250 and rows["MainStatus"]["frames_per_s"] == 10
    total = load["total"]
    assert total["load_worst"] == pytest.approx(sum(r["load_worst"] for r in load["rows"]))
    unstuffed = sum(r["frames_per_s"] * can_frame_bits(r["bytes"], worst_case=False) for r in load["rows"])
    assert unstuffed / 1e6 < total["load_typical"] < total["load_worst"] < 0.5  # a bus with headroom
    assert total["slcan_bytes_per_s"] > 0


# ------------------------------------------------------------------------------ measured load
def _sdo_write(node: int, index: int, value: int, size: int, sub: int = 0) -> bytes:
    cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = struct.pack("<BHB", cmd, index, sub) + value.to_bytes(size, "little").ljust(4, b"\0")
    return slcan.encode_frame(CanFrame(0x600 + node, data))


def _configure(node: int) -> bytes:
    """The SDO writes CanDrives makes (CiA 301's mapping procedure: disable, clear, map, count, enable), and
    the 100 ms heartbeat, as slcan lines."""
    lines = [_sdo_write(node, 0x1017, 100, 2)]
    for comm, objects, kind in ((0x1800, (0x60410010, 0x60640020), 1), (0x1801, (0x606C0020, 0x60770010), 1),
                                (0x1401, (0x607A0020,), 255)):  # fmt: skip
        cob = {0x1800: 0x180, 0x1801: 0x280, 0x1401: 0x300}[comm] + node
        mapping = comm + 0x200
        lines.append(_sdo_write(node, comm, cob | 0x8000_0000, 4, sub=1))
        lines.append(_sdo_write(node, mapping, 0, 1))
        lines += [_sdo_write(node, mapping, o, 4, sub=k + 1) for k, o in enumerate(objects)]
        lines.append(_sdo_write(node, mapping, len(objects), 1))
        lines.append(_sdo_write(node, comm, kind, 1, sub=2))
        lines.append(_sdo_write(node, comm, cob, 4, sub=1))
    return b"".join(lines)


def _read_until(rig: Rig, adapter: A.SlcanAdapter, t: float, until: float) -> tuple[float, list[CanFrame]]:
    """The host reading the adapter every millisecond (USB CDC: its receive FIFO never overruns) from ``t``
    to ``until``: (``until``, the frames read)."""
    buffer, frames = bytearray(), []
    while t < until:
        t = min(until, t + 1e-3)
        rig.advance(t)
        buffer += adapter.poll(t)
        frames += [slcan.parse_frame(line) for line in slcan.split_lines(buffer)]
    return t, frames


def _popup_bus(sync_hz: float, seconds: float, settle_s: float = 0.15) -> tuple[Rig, A.SlcanAdapter, dict]:
    """POPUP's rig in simulated time with a host that opens the adapter, configures and starts the drives,
    then sends one SYNC and a target RPDO per drive every 1/``sync_hz`` for ``seconds``; the bus's counters
    over those seconds, and the frames that reached the host (``received``)."""
    rig = Rig(load_robot("popup"))
    adapter = rig.emulators["can_bus"]
    ids = sorted(rig.drives)
    t = 0.05
    adapter.feed(b"S8\r\rO\r", t)
    for node in ids:  # one drive at a time, as the driver does: each waits for its answers
        adapter.feed(_configure(node), t)
        t = _read_until(rig, adapter, t, t + 0.02)[0]
    adapter.feed(slcan.encode_frame(CanFrame(0x000, bytes([0x01, 0]))), t)  # NMT: start every node
    t = _read_until(rig, adapter, t, settle_s)[0]
    before = dict(vars(rig.can_bus.counters))
    received: list[CanFrame] = []
    period = 1.0 / sync_hz
    targets = b"".join(slcan.encode_frame(CanFrame(0x300 + n, b"\0\0\0\0")) for n in ids)
    k, end = 0, t + seconds
    while t < end:
        adapter.feed(b"t0800\r" + targets, t)
        k += 1
        t, frames = _read_until(rig, adapter, t, settle_s + k * period)
        received += frames
    c = rig.can_bus.counters
    over = {key: getattr(c, key) - before[key] for key in before if key != "max_wait_s"}
    return rig, adapter, {**over, "seconds": seconds, "received": received, "max_wait_s": c.max_wait_s}


def test_the_bus_measures_the_load_computed_from_the_description():
    robot = load_robot("popup")
    computed = popup_can_load(robot)
    rig, adapter, got = _popup_bus(robot.devices["can_bus"].rate_hz, seconds=1.0)
    measured = got["busy_s"] / got["seconds"]
    frames_s = got["frames"] / got["seconds"]
    assert frames_s == pytest.approx(computed["total"]["frames_per_s"], rel=0.02)
    assert measured == pytest.approx(computed["total"]["load_typical"], rel=0.05)  # measured: 3.6 % above
    assert measured < computed["total"]["load_worst"]
    assert got["lost"] == 0 and rig.can_bus.dropped == {}
    assert adapter.counters.tx_dropped == adapter.counters.rx_overrun == 0
    # a shared bus: the host's frames sometimes wait for a drive's, which the status flags say, and no more
    assert int(adapter.feed(b"F\r", rig.world.t)[1:3], 16) & ~A.ARBITRATION_LOST == 0


def test_a_sync_rate_above_the_bus_delays_and_loses_frames_and_counts_them():
    """SYNC at 1.5 kHz asks for about 160 % of 1 Mbit/s: the bus runs full, the lowest priorities wait
    longest and the nodes' transmit queues overflow; the host's adapter refuses what its queue cannot take
    and says so in its status flags. The highest priorities (SYNC, the TPDO1s) still go every cycle."""
    robot = load_robot("popup")
    sync_hz = 1500.0
    load = popup_can_load(robot)
    asked = load["total"]["load_typical"] + (sync_hz / load["sync_hz"] - 1) * sum(
        r["load_typical"] for r in load["rows"] if r["frame"] in ("SYNC", "TPDO1", "TPDO2", "RPDO2")
    )
    assert asked > 1.3
    rig, adapter, got = _popup_bus(sync_hz, seconds=0.5)
    busy = got["busy_s"] / got["seconds"]
    assert busy > 0.97  # the bus never idles
    assert got["lost"] > 0 and got["delayed"] > 0 and got["arbitration_lost"] > 0
    assert got["max_wait_s"] > 1.0 / sync_hz  # a frame waited longer than a cycle
    dropped = rig.can_bus.dropped
    assert dropped.get("host", 0) > 0 and adapter.counters.tx_dropped == dropped["host"]
    flags = int(adapter.feed(b"F\r", rig.world.t)[1:3], 16)
    assert flags & A.TX_FULL and flags & A.ARBITRATION_LOST
    assert adapter.feed(b"F\r", rig.world.t) == b"F00\r"  # read, the latched flags clear
    # the boards' lost frames are holes in the sample numbers the recorder numbers their samples by
    boards = BoardFrames({"main_board": 0x10, "link1_board": 0x11, "link2_board": 0x12},
                         {"main_board": 0.1, "link1_board": 0.01, "link2_board": 0.01})  # fmt: skip
    network = canopen.Network()
    boards.attach(network)
    for frame in got["received"]:
        network.notify(frame.can_id, bytearray(frame.data), 0.0)
    seqs: dict[str, list[int]] = {}
    for sample in boards.take():
        seqs.setdefault(sample.message, []).append(sample.seq)
    holes = sum(s[-1] - s[0] + 1 - len(s) for s in seqs.values())
    lost_by_boards = sum(n for name, n in dropped.items() if "board" in name)
    sent = {"Link2Accel", "MainPressure", "MainStatus", "Link1Orientation", "Link2Orientation", "Link1Flex",
            "Link2Flex"}  # fmt: skip
    starved = sent - set(seqs)
    assert lost_by_boards > 0 and holes <= lost_by_boards
    # each lost frame is a hole in its stream's numbers, or its stream starved outright: the lowest
    # priorities (the flex frames, 0x391 and 0x392), whose silence the recorder sees as a stream with nothing
    assert holes > 0 or starved
    assert starved <= {"Link1Flex", "Link2Flex"}
    # what arbitration favours still gets through: every drive's TPDO1 (0x181–0x183) each SYNC it saw
    syncs = got["seconds"] * sync_hz
    assert got["frames"] > 0.9 * syncs * 4


class Listener(CanNode):
    """A node that only listens."""

    def __init__(self) -> None:
        self.heard: list[CanFrame] = []

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        self.heard.append(frame)
        return []


class Periodic(CanNode):
    """A node sending ``frame`` every ``period_s``."""

    def __init__(self, name: str, frame: CanFrame, period_s: float) -> None:
        self.name, self.frame, self.period_s, self.k = name, frame, period_s, 0

    def next_due_s(self) -> float:
        return self.k * self.period_s

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        out = []
        while self.next_due_s() <= t:
            out.append((self.next_due_s(), self.frame))
            self.k += 1
        return out


def test_only_the_lower_priority_loses_on_an_overloaded_bus_and_a_late_look_loses_nothing_more():
    """Two nodes each offering 60 % of the bus: the lower identifier goes every time, the other gets what
    is left (40 %) and loses the rest on its full queue. Playing the bus in one call or in small steps
    gives the same counts: frames are offered at their due times, not all at once when the bus is read."""

    def run(step_s: float) -> CanBus:
        bits = can_frame_exact_bits(CanFrame(0x100, b"\x55" * 8))
        period = bits / 0.6e6
        high = Periodic("high", CanFrame(0x100, b"\x55" * 8), period)
        low = Periodic("low", CanFrame(0x101, b"\x55" * 8), period)
        bus = CanBus(1_000_000, [high, low])
        t = 0.0
        while t < 1.0:
            t = min(1.0, t + step_s)
            bus.run_until(t)
        return bus

    one, many = run(1.0), run(1e-4)
    assert one.dropped == many.dropped and one.counters.frames == many.counters.frames
    assert "high" not in one.dropped
    sent = one.counters.frames
    assert one.dropped["low"] == pytest.approx(sent * 0.2 / 1.0, rel=0.1)  # 120 % offered, 20 % lost
    assert one.counters.busy_s > 0.99


def test_the_adapter_sends_the_hosts_frames_in_the_order_the_host_sent_them():
    """Its firmware queue is a FIFO: a low identifier sent after a high one waits behind it (a node's
    mailboxes would send it first), and the queue's 64 frames are all it takes before refusing more."""
    listener = Listener()
    bus = CanBus(1_000_000, [listener])
    adapter = A.SlcanAdapter(bus)
    adapter.feed(b"S8\rO\r", 0.0)
    replies = adapter.feed(b"t3000\r" + b"t1000\r" * (A.TX_QUEUE - 1) + b"t0500\r", 0.0)
    assert replies == b"z\r" * A.TX_QUEUE + slcan.BEL  # the 65th refused
    adapter.poll(1.0)
    assert [f.can_id for f in listener.heard] == [0x300] + [0x100] * (A.TX_QUEUE - 1)
    assert adapter.counters.tx_dropped == 1 and int(adapter.feed(b"F\r", 1.0)[1:3], 16) & A.TX_FULL


def test_the_twin_answering_late_loses_none_of_the_frames_the_bus_carried_meanwhile():
    """The rig looked at again only after 0.3 s (its process not scheduled: a busy machine) passes on every
    frame the bus carried in that while: a real adapter sent them to the host every millisecond, and the
    twin's own lateness is not a host that stopped reading (a CI run lost a board's pressure sample to it)."""
    rig = Rig(load_robot("popup"))
    adapter = rig.emulators["can_bus"]
    adapter.feed(b"S8\rO\r", 0.0)
    boards = BoardFrames({"main_board": 0x10, "link1_board": 0x11, "link2_board": 0x12},
                         {"main_board": 0.1, "link1_board": 0.01, "link2_board": 0.01})  # fmt: skip
    network = canopen.Network()
    boards.attach(network)
    frames = _read_until(rig, adapter, 0.0, 0.1)[1]
    rig.advance(0.4)
    frames += [slcan.parse_frame(line) for line in slcan.split_lines(bytearray(adapter.poll(0.4)))]
    for frame in frames:
        network.notify(frame.can_id, bytearray(frame.data), 0.0)
    seqs: dict[str, list[int]] = {}
    for sample in boards.take():
        seqs.setdefault(sample.message, []).append(sample.seq)
    assert seqs["Link2Accel"][-1] - seqs["Link2Accel"][0] > 300  # 1 kHz: the late look's 0.3 s included
    assert all(s == list(range(s[0], s[0] + len(s))) for s in seqs.values()), "a hole in a board's numbers"
    assert adapter.counters.rx_overrun == 0 and rig.can_bus.counters.lost == 0
