"""POPUP's main board and link boards on the CAN bus, through the real stack (python-can slcan, canopen's
network, cantools and the DBC) against the rig; and a POPUP session recorded from the rig, read by both MCAP
readers. Rates are checked with wide margins and times are generous: the rig runs in its own process, and the
machine may be busy."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from machine_stalls import cpu_stolen_s

from acquisition.codecs import popup_boards as pb
from acquisition.codecs.can import CanFrame
from acquisition.devices.can_drives import CanDrives
from acquisition.devices.popup_boards import BoardFrames, BoardLostError
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from twin.ptyhost import send_control

IDS = {"q1": 1, "q2": 2, "q3": 3}
BOARDS = {"main_board": 0x10, "link1_board": 0x11, "link2_board": 0x12}
PERIODS = {"main_board": 0.1, "link1_board": 0.01, "link2_board": 0.01}


@pytest.fixture
def bus(popup_rig):
    run_dir, port = popup_rig
    with CanDrives(port, IDS) as drives:
        boards = BoardFrames(BOARDS, PERIODS)
        boards.attach(drives.network)
        yield drives, boards
        boards.detach()
    send_control(run_dir, {"op": "can", "board": "link2_board", "power": True})


def _collect(boards: BoardFrames, seconds: float) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.05)
        out += boards.take()
    return out + boards.take()


@pytest.mark.slow
def test_board_frames_arrive_numbered_at_their_rates(bus, real_time):
    _, boards = bus
    boards.take()
    # two seconds: a reader held up ~0.3 s on a busy machine gets the held frames in one burst, and over one
    # second that read as 1,450 frames/s of the 1 kHz accelerometer (the device's rate, by its numbers, held)
    samples = _collect(boards, 2.0)
    real_time()  # a host that took the CPUs from python-can's reader lets the adapter's buffer overflow
    by_message: dict[str, list] = {}
    for s in samples:
        by_message.setdefault(s.message, []).append(s)
    expected_hz = {"Link2Accel": 1000, pb.MAIN_PRESSURE: 250, "Link1Orientation": 100, "Link1Flex": 100,
                   "Link2Orientation": 100, "Link2Flex": 100}  # fmt: skip
    assert "Link1Accel" not in by_message  # only link 2's board carries the arm's accelerometer
    for message, hz in expected_hz.items():
        got = by_message[message]
        seq = np.array([s.seq for s in got])
        assert (np.diff(seq) == 1).all(), message  # every sample, in order, none lost
        span_s = (got[-1].host_ns - got[0].host_ns) / 1e9
        assert len(got) / max(span_s, 1e-3) == pytest.approx(hz, rel=0.3), message
    flex = by_message["Link1Flex"][-1].signals
    assert all(0 <= flex[f"Flex{i}"] <= 4095 for i in range(1, 5))
    accel = [[s.signals[a] for a in ("AccelX", "AccelY", "AccelZ")] for s in by_message["Link2Accel"]]
    assert np.linalg.norm(np.mean(accel, axis=0)) == pytest.approx(9.81, abs=0.5)  # on average: gravity


@pytest.mark.slow
def test_the_main_board_regulates_to_the_commanded_set_points(bus, popup_rig):
    run_dir, _ = popup_rig
    _, boards = bus
    boards.send_pressures([40_000.0, 60_000.0], [True, True])
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        state = send_control(run_dir, {"op": "state"})
        if state["pressure_set_pa"] == [40_000.0, 60_000.0]:
            break
        time.sleep(0.05)
    assert state["pressure_set_pa"] == [40_000.0, 60_000.0]
    time.sleep(1.5)  # the regulators' time constant is 0.2 s
    pressure = [s for s in _collect(boards, 0.3) if s.message == pb.MAIN_PRESSURE][-1]
    assert pressure.signals["Regulate1"] == pressure.signals["Regulate2"] == 1
    counts = np.array([pressure.signals["Link1Counts"], pressure.signals["Link2Counts"]])
    from models.robot import load_robot

    measured = load_robot("popup").sensors.pressure.counts_to_pa(counts)
    np.testing.assert_allclose(measured, [40_000.0, 60_000.0], atol=2_000.0)


def test_a_set_point_beyond_the_regulators_is_rejected_by_the_board(bus, popup_rig):
    run_dir, _ = popup_rig
    drives, boards = bus
    before = send_control(run_dir, {"op": "state"})["pressure_set_pa"]
    status = [s for s in _collect(boards, 0.3) if s.message == pb.MAIN_STATUS][-1]
    frame = pb.encode(pb.PRESSURE_COMMAND, {"Setpoint1": 120_000, "Setpoint2": 0, "Regulate1": 1,
                                            "Regulate2": 1, "Counter": 1})  # fmt: skip
    drives.network.send_message(frame.can_id, frame.data)  # past the host's guard: the board's own check
    after = [s for s in _collect(boards, 0.5) if s.message == pb.MAIN_STATUS][-1]
    assert after.signals["Rejected"] == status.signals["Rejected"] + 1
    assert send_control(run_dir, {"op": "state"})["pressure_set_pa"] == before


def test_a_board_whose_frames_stop_is_detected(bus, popup_rig):
    run_dir, _ = popup_rig
    _, boards = bus
    boards.check()
    send_control(run_dir, {"op": "can", "board": "link2_board", "power": False})
    with pytest.raises(BoardLostError, match="link2_board"):
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            boards.take()
            boards.check()
            time.sleep(0.05)


def test_a_frame_that_is_not_the_dbc_s_is_refused_by_the_codec():
    with pytest.raises(Exception, match="not a board frame"):
        pb.decode(0x190, b"\x01")  # MainPressure is 8 bytes
    assert CanFrame(0x190, b"\x00" * 8).can_id in pb.frame_ids()


@pytest.mark.slow
def test_a_popup_session_recorded_from_the_rig_reads_in_both_mcap_readers(tmp_path, ros2_agrees, real_time):
    """``vslab record --robot popup --rig``: every stream of the bus (drives, main board, link boards) and the
    tracker: the boards' streams without a hole, the polled ones (joint states, tracker frames) nearly so, the
    session's account counting exactly the holes, and the fast reader and mcap-ros2-support agreeing."""
    lab = tmp_path / "lab"
    cli = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "--quiet"]
    stolen_s = cpu_stolen_s()
    done = subprocess.run([*cli, "record", "--robot", "popup", "--rig", "--duration", "3", "--session", "p"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    stolen_ms = (cpu_stolen_s() - stolen_s) * 1e3  # said with a failure below: a CI run once recorded no CAN
    assert done.returncode == 0, done.stderr[-2000:]  # frame at all (the bus daemon silent for 15 s)
    part = lab / "sessions" / "p" / "p_000.mcap"
    data = read_fixed_topics(part)
    counters = json.loads((part.parent / "session.json").read_text())["counters"]
    holes = {}
    for topic in (T.PRESSURE, T.ACCEL, "/link1/orientation", "/link2/flex", T.JOINT_STATE, T.TRACKER):
        seq = np.sort(data[topic].rows["seq" if topic != T.TRACKER else "frame"].astype(np.int64))
        holes[topic] = (int((np.diff(seq) - 1).sum()), len(seq))
        # every sample the device sent is in the file or counted: never taken from the device (lost) or taken
        # and never written (dropped: the writer fell behind and its ring was full). Those leave holes, or a
        # shorter head or tail where the ring was full then (a CI run dropped 103 accel samples mid-file;
        # another, whose accel ring held 3 s instead of 30, its last 497: both counted). Always true, however
        # long the hypervisor stalled the machine.
        c = counters[topic]
        assert c["expected"] == c["written"] + c["lost"] + c["dropped"], (topic, c)
        assert c["received"] == c["written"] + c["dropped"] and c["written"] == len(data[topic]), (topic, c)
        assert holes[topic][0] <= c["lost"] + c["dropped"], (topic, c)
    # a CI run whose 3 s recording had 9.7 s taken by the hypervisor recorded no joint state at all: what the
    # host can miss is the host's to give
    real_time()
    for topic in (T.JOINT_STATE, T.PRESSURE, T.ACCEL, "/link1/orientation", "/link2/flex", T.TRACKER):
        events = [f"{e.kind.name} {e.text}" for _, e in read_events(part)]
        assert len(data[topic]) > 0, f"{topic}: none recorded; {stolen_ms:.0f} ms stolen; events {events}"
    joints = data[T.JOINT_STATE].rows
    assert (joints["statusword"] & 0x6F == 0x27).all()
    assert np.isfinite(joints["position"]).all()
    assert ros2_agrees(part)[T.ACCEL] == len(data[T.ACCEL])
    for topic, (missed, got) in holes.items():
        if topic in (T.JOINT_STATE, T.TRACKER):
            # polled: a SYNC some drive left unanswered (even after the next SYNC waited a period for it),
            # a tracker frame that came and went between two polls (round trips at 115200 Bd) are holes
            assert missed <= 0.03 * got, f"{topic}: {missed} of {got + missed} lost"
        else:
            assert missed == 0, topic  # the boards send on their own: nothing a busy host can miss


def test_every_board_stream_has_thirty_seconds_of_ring(popup):
    """The writer may stall for RING_SECONDS before a stream loses anything: the bus's rings are sized by
    each stream's own rate (the accelerometer's 1 kHz), not by the SYNC's 100 Hz."""
    from acquisition.recorder.layout import DeviceEntry
    from acquisition.recorder.recorder import RING_SECONDS, ring_slots
    from acquisition.recorder.sources import make_source

    source = make_source(popup, "can_bus", "unopened", None)
    entry = DeviceEntry("can_bus", source.driver, "unopened", source.rate_hz, list(source.topics),
                        list(source.sampled_topics), source.sampled_rates_hz)  # fmt: skip
    rates = {T.ACCEL: popup.sensors.accelerometer.sample_rate_hz, T.JOINT_STATE: source.rate_hz}
    for topic, hz in rates.items():
        assert ring_slots(entry, topic) >= RING_SECONDS * hz, topic
    assert ring_slots(entry, T.ACCEL) >= 10 * ring_slots(entry, T.JOINT_STATE)


@pytest.mark.parametrize(
    "cmd",
    [{"op": "can", "board": "main_board", "power": "off"}, {"op": "can", "board": "main_board"},
     {"op": "can", "board": "nope", "power": False}, {"op": "can", "bus_off": 1}],
)  # fmt: skip
def test_the_rig_refuses_a_malformed_can_fault(popup, cmd):
    from twin.rig import Rig

    rig = Rig(popup)
    with pytest.raises(ValueError):
        rig.control(cmd)
    assert not any(b.silent for b in rig.boards.values()) and not rig.can_bus.bus_off
