"""The event-driven rig: emulators say when their next output is due, the host sleeps until then, the twin
steps only when a device needs it, and a Sync Read senses the twin once per step."""

import json
import os
import time

import numpy as np
import pytest
from conftest import emulator_host

from acquisition.codecs import board_lines as bp
from acquisition.codecs import dynamixel as dx
from twin import sensors, streams
from twin.emulators.base import LEGACY_POLL_S, Emulator
from twin.emulators.board_firmware import PressureBoardEmulator, StepperBoardEmulator
from twin.emulators.board_hardware import SimplePressureHardware, SimpleStepperHardware
from twin.emulators.dynamixel import demo_bus
from twin.ptyhost import PORTS_FILE, send_control
from twin.rig import Rig

RIG = ("--robot", "vsl")


def _ask(emu, body: str, now_s: float) -> str:
    return bp.decode(emu.feed(bp.encode(body), now_s))


def _lines(out: bytes) -> list:
    return [bp.parse_message(bp.decode(line + b"\n")) for line in out.splitlines()]


def _run_events(emu, start_s: float, end_s: float):
    """Drive ``emu`` the way the pty host does: jump to each ``next_output_s`` and poll there.
    Returns the streamed lines and how many polls found nothing due (early wake-ups)."""
    now, lines, empty = start_s, [], 0
    while True:
        due = emu.next_output_s(now)
        assert due is not None
        if due > end_s:
            return lines, empty
        now = max(now, due)
        got = _lines(emu.poll(now))
        assert len(got) <= 1, "at most one line per loop"
        if got:
            lines += got
        else:
            empty += 1
            assert emu.next_output_s(now) > now, "a wake-up that found nothing due must not spin"


# --------------------------------------------------------------------------- next_output_s, no pty
def test_board_next_output_s_ready_then_nothing_until_a_stream():
    emu = PressureBoardEmulator(SimplePressureHardware())
    assert emu.next_output_s(0.0) == 0.0, "READY is due at power-up"
    assert _lines(emu.poll(0.0))[0].board == bp.BOARD_PRESSURE
    assert emu.next_output_s(0.01) is None, "not streaming: nothing scheduled, the host may sleep"
    assert _ask(emu, "1 STREAM 100", 0.5) == "OK 1 STREAM"
    assert emu.next_output_s(0.5) == 0.5, "the first line on the next loop"
    assert _ask(emu, "2 STREAM 0", 0.6) == "OK 2 STREAM"
    assert emu.next_output_s(0.6) is None


@pytest.mark.parametrize("offset_s", [0.0, 4294.9])  # the second one wraps micros() during the run
def test_board_next_output_s_is_exact_on_the_drifting_clock(offset_s):
    hw = SimplePressureHardware(drift_ppm=1500.0, offset_s=offset_s)
    emu = PressureBoardEmulator(hw)
    emu.poll(0.0)
    _ask(emu, "1 STREAM 100", 0.0)
    first = _lines(emu.poll(0.0))[0]
    due = emu.next_output_s(0.0)
    target = (first.micros + 10_000) % bp.MICROS_MODULO
    assert hw.micros(due) == target, "due exactly when the board's clock reaches the next period"
    assert hw.micros(due - 1e-6) != target, "and not a microsecond earlier"
    assert due == pytest.approx(0.01 / 1.0015, abs=1e-6), "10 ms of board clock, 1500 ppm fast"
    lines, empty = _run_events(emu, 0.0, 10.0)
    lines = [first, *lines]
    assert empty == 0, "no early wake-ups with an exact clock inverse"
    assert [s.seq for s in lines] == list(range(len(lines)))
    gaps = np.diff(np.array([s.micros for s in lines], dtype=np.int64)) % bp.MICROS_MODULO
    assert set(gaps.tolist()) == {10_000}, "on the board's rate, on the board's clock, nothing skipped"
    assert len(lines) == pytest.approx(10.0 * 1.0015 * 100, abs=1.5)


def test_stepper_board_next_output_s():
    emu = StepperBoardEmulator(SimpleStepperHardware(drift_ppm=40.0))
    emu.poll(0.0)
    _ask(emu, "1 STREAM 200", 0.0)
    lines, empty = _run_events(emu, 0.0, 2.0)
    assert empty == 0 and len(lines) == pytest.approx(2.0 * 1.00004 * 200, abs=1.5)
    assert set(np.diff([s.micros for s in lines]).tolist()) == {5000}


def test_emulators_without_unsolicited_output_schedule_nothing():
    assert demo_bus().next_output_s(1.0) is None

    class Legacy(Emulator):  # streams but cannot say when: polled every millisecond, as before
        def poll(self, now_s: float) -> bytes:
            return b"x"

    assert Legacy().next_output_s(2.0) == 2.0 + LEGACY_POLL_S


# ------------------------------------------------------------------------------- the twin, no pty
@pytest.fixture
def rig(vsl):
    return Rig(vsl, seed=5)


def test_rig_ticks_are_the_clock_models_counts(rig):
    times = np.concatenate([np.random.default_rng(0).uniform(0, 5000, 2000), np.arange(0.0, 3.0, 0.001)])
    for t in times:
        rig.world.state.t = float(t)
        for name, clock in rig.world.clocks.items():
            assert rig.ticks(name) == int(clock.ticks_at(np.array([0]), np.array([t]))[0])


def test_twin_board_streams_on_the_twins_clock_without_stepping_ahead(rig):
    emu = rig.emulators["pressure_board"]
    emu.poll(0.0)
    _ask(emu, "1 STREAM 250", 0.0)
    lines, empty = _run_events(emu, 0.0, 5.0)
    assert empty <= 5, "the twin's clock inverse is exact but for rare float ties at a step boundary"
    assert rig.steps <= 5000, "the twin is never stepped past the rig time"
    assert [s.seq for s in lines] == list(range(len(lines)))
    micros = np.array([s.micros for s in lines], dtype=np.int64)
    period, step_us = 4000, 1000 * (1 + abs(rig.world.clocks["pressure_board"].drift_ppm[0]) * 1e-6) + 1
    scheduled = micros[0] + period * np.arange(len(micros))  # the board's schedule: every 4 ms of its clock
    late = (micros - scheduled) % bp.MICROS_MODULO
    assert late.max() < step_us, "each line in the twin step where its period came due: none skipped"
    drift = rig.world.clocks["pressure_board"].drift_ppm[0] * 1e-6
    assert len(lines) == pytest.approx(5.0 * (1 + drift) * 250, abs=2)


def test_a_sync_read_senses_the_twin_once_per_step(rig, monkeypatch):
    bus = rig.emulators["servo_bus"]
    ids = sorted(bus.tables)
    calls = []
    original = streams.servo_counts
    monkeypatch.setattr(streams, "servo_counts", lambda *a: calls.append(a[1].shape) or original(*a))
    request = dx.instruction(dx.BROADCAST_ID, dx.SYNC_READ, bytes([120, 0, 16, 0, *ids]))
    reply = bus.feed(request, 0.0105)
    assert calls == [(len(ids),)], "one vectorised sensing for all the servos"
    assert bus.feed(request, 0.0107) == reply, "same step: the same reading"
    assert len(calls) == 1
    replies = dx.PacketReader().feed(bus.feed(request, 0.0115))
    assert len(calls) == 2 and [p.dxl_id for p in replies] == ids
    for packet, dxl_id in zip(replies, ids, strict=True):
        table = bus.tables[dxl_id]
        assert packet.params == bytes(table.data[120:136])
        assert table.get(dx.REALTIME_TICK) == rig.ticks("servo_bus") % 32768
        joint = rig.emulators["servo_bus"].hardware.joints[dxl_id]
        angle = rig.world.state.out_pos[0, joint]
        assert table.get(dx.PRESENT_POSITION, signed=True) == sensors.encoder_counts(
            angle, rig.robot.servo.zero_count
        )


def test_twin_stays_deterministic_for_a_seed(vsl):
    def session(seed: int) -> bytes:
        rig = Rig(vsl, seed=seed)
        bus, board = rig.emulators["servo_bus"], rig.emulators["pressure_board"]
        request = dx.instruction(dx.BROADCAST_ID, dx.SYNC_READ, bytes([120, 0, 16, 0, *sorted(bus.tables)]))
        out = board.poll(0.0) + board.feed(bp.encode("1 STREAM 250"), 0.0)
        for k in range(200):
            now = 0.0005 * k
            out += bus.feed(request, now) + board.poll(now)
        return out

    assert session(3) == session(3)
    assert session(3) != session(4)


# --------------------------------------------------------------------------------- the rig on ptys
def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wakeups(pid: int) -> int:
    total = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/status") as f:
            total += sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
    return total


@pytest.fixture(scope="module")
def live_rig(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("rig-events") / "run"
    with emulator_host(run_dir, module="twin.rig", extra=RIG) as ports:
        pid = json.loads((run_dir / PORTS_FILE).read_text())["pid"]
        yield run_dir, ports, pid


@pytest.mark.slow
@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="reads the rig's CPU time from /proc")
def test_an_idle_rig_sleeps(live_rig):
    _, _, pid = live_rig
    time.sleep(0.5)  # start-up work done
    cpu0, wake0, t0 = _cpu_s(pid), _wakeups(pid), time.monotonic()
    time.sleep(2.0)
    cpu, wakes, wall = _cpu_s(pid) - cpu0, _wakeups(pid) - wake0, time.monotonic() - t0
    assert wakes / wall < 100, f"{wakes / wall:.0f} wake-ups/s: the host polls instead of sleeping"
    assert cpu / wall < 0.05, f"an idle rig used {100 * cpu / wall:.1f} % of a core"


def test_control_commands_see_the_present(live_rig):
    run_dir, _, _ = live_rig
    t1, w1 = send_control(run_dir, {"op": "state"})["t"], time.monotonic()
    time.sleep(0.2)
    t2, w2 = send_control(run_dir, {"op": "state"})["t"], time.monotonic()
    assert t2 - t1 == pytest.approx(w2 - w1, abs=0.02), "the twin is brought up to now before a command"


@pytest.mark.slow
def test_streamed_lines_at_the_boards_rate_with_consecutive_seq(live_rig, real_time):
    from acquisition.devices.boards import PressureBoard, StepperBoard

    _, ports, _ = live_rig
    with PressureBoard(ports["pressure_board"]) as pb, StepperBoard(ports["stepper_board"]) as sb:
        boards = {pb: 250, sb: 100}
        for board, hz in boards.items():
            board.start_stream(hz)
        samples = {board: [] for board in boards}
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            time.sleep(0.02)
            for board in boards:
                samples[board] += board.read_samples()
        real_time()  # a board skips the periods a stalled rig missed, as the firmware does
        for board, hz in boards.items():
            board.stop_stream()
            got = samples[board]
            assert len(got) > hz, f"{board.kind}: {len(got)} lines in 2 s at {hz} Hz"
            assert np.all(np.diff([s.seq for s in got]) == 1), "consecutive sequence numbers"
            gaps = np.diff(np.array([s.micros for s in got], dtype=np.int64)) % bp.MICROS_MODULO
            period = 1_000_000 // hz
            ahead = period * np.arange(1, len(gaps) + 1) - np.cumsum(gaps)  # of the board's own schedule
            assert ahead.max() < 1100, (
                "never faster than the rate (a late line may be followed by an early-looking one)"
            )
            rate = len(gaps) / (gaps.sum() * 1e-6)
            assert 0.9 * hz < rate < 1.001 * hz, (
                "the board's rate on its clock (a line >1 period late is skipped)"
            )
