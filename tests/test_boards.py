"""The Arduino boards: line codec, PROTOCOL.md examples, emulators byte for byte, drivers over a real pty."""

from __future__ import annotations

import itertools
import re
import time
from pathlib import Path

import pytest

from acquisition.devices.boards import PressureBoard, StepperBoard
from acquisition.errors import DeviceNotFoundError, DeviceReplyError
from acquisition.protocols import boards as bp
from acquisition.sim.emulators.boards import (
    PressureBoardEmulator,
    SimplePressureHardware,
    SimpleStepperHardware,
    StepperBoardEmulator,
)

PROTOCOL_MD = Path(__file__).resolve().parents[1] / "firmware" / "PROTOCOL.md"
PRESSURE = "pressure_board=acquisition.sim.emulators.boards:demo_pressure_board"
STEPPER = "stepper_board=acquisition.sim.emulators.boards:demo_stepper_board"


# ------------------------------------------------------------------------------------------- codec
def test_checksum_encode_decode_round_trip():
    assert bp.checksum(b"") == 0
    assert bp.checksum(b"AB") == 0x41 ^ 0x42
    line = bp.encode("7 SET 0 150000")
    assert line.endswith(b"\n") and re.fullmatch(rb"7 SET 0 150000\*[0-9A-F]{2}\n", line)
    assert bp.decode(line) == "7 SET 0 150000"
    assert bp.decode(line[:-1] + b"\r\n") == "7 SET 0 150000"


@pytest.mark.parametrize("index", [0, 3, 10])
def test_corrupted_line_rejected(index):
    line = bytearray(bp.encode("P 12 345678 16000 4000 1"))
    line[index] ^= 0x01
    with pytest.raises(bp.BoardChecksumError):
        bp.decode(bytes(line))


@pytest.mark.parametrize("bad", [b"OK 1 SET\n", b"OK 1 SET*7\n", b"OK 1 SET*ZZ\n", b"x" * 80 + b"*00\n"])
def test_malformed_lines_rejected(bad):
    with pytest.raises(bp.BoardChecksumError):
        bp.decode(bad)


def test_encode_refuses_bodies_the_protocol_cannot_carry():
    for body in ("a*b", "x" * 64, "tab\there"):
        with pytest.raises(ValueError):
            bp.encode(body)


def test_every_example_in_protocol_md_parses():
    blocks = re.findall(r"```text\n(.*?)```", PROTOCOL_MD.read_text(), flags=re.S)
    lines = [line for block in blocks for line in block.splitlines() if line[:2] in ("> ", "< ")]
    assert len(lines) > 30
    kinds = set()
    for line in lines:
        body = bp.decode(line[2:].encode() + b"\n")
        if line.startswith(">"):
            bp.parse_command(body)
        else:
            kinds.add(type(bp.parse_message(body)))
    assert kinds == {bp.Ok, bp.Err, bp.Ident, bp.Position, bp.Ready, bp.PressureLine, bp.StepperLine}


# --------------------------------------------------------------------------------------- emulators
def _ask(emulator, body: str, now_s: float = 0.0) -> str:
    reply = emulator.feed(bp.encode(body), now_s)
    assert reply.count(b"\n") == 1
    return bp.decode(reply)


def test_pressure_emulator_commands():
    emu = PressureBoardEmulator(SimplePressureHardware())
    assert _ask(emu, "1 ID?") == "ID 1 PRESSURE 1.0.0 VSLP-0001"
    assert _ask(emu, "2 SET 0 150000") == "OK 2 SET"
    assert emu.hw.setpoint_pa[0] == 150000.0
    assert _ask(emu, "3 VALVE 1 1") == "OK 3 VALVE" and emu.valves == 2
    assert _ask(emu, "4 SET 0 500000") == "ERR 4 5 RANGE"
    assert _ask(emu, "5 SET 0 abc") == "ERR 5 4 ARGS"
    assert _ask(emu, "6 MOVE 10") == "ERR 6 3 UNKNOWN"
    assert _ask(emu, "7 STOP") == "OK 7 STOP" and emu.valves == 0 and emu.hw.setpoint_pa == [0.0, 0.0]


def test_bad_checksum_and_split_input():
    emu = PressureBoardEmulator(SimplePressureHardware())
    assert bp.decode(emu.feed(b"1 ID?*00\n", 0.0)) == "ERR - 1 CHECKSUM"
    assert bp.decode(emu.feed(b"1 ID?*G0\n", 0.0)) == "ERR - 2 MALFORMED"
    assert bp.decode(emu.feed(b"garbage\n", 0.0)) == "ERR - 2 MALFORMED"
    assert bp.decode(emu.feed(b"y" * 200 + b"\n", 0.0)) == "ERR - 2 MALFORMED"
    line = bp.encode("9 ID?")
    assert emu.feed(line[:3], 0.0) == b""
    assert bp.decode(emu.feed(line[3:], 0.0)).startswith("ID 9 PRESSURE")


def test_stream_rate_respected_on_the_board_clock():
    emu = PressureBoardEmulator(SimplePressureHardware(drift_ppm=1500.0))
    emu.poll(0.0)  # READY
    assert _ask(emu, "1 STREAM 100") == "OK 1 STREAM"
    samples = []
    for k in range(1, 20001):  # 10 s of host time, polled every 0.5 ms
        out = emu.poll(k * 0.0005)
        samples += [bp.parse_message(bp.decode(line + b"\n")) for line in out.splitlines()]
    assert all(isinstance(s, bp.PressureLine) for s in samples)
    assert 1001 <= len(samples) <= 1003  # 10 s × 1.0015 × 100 Hz
    assert [s.seq for s in samples] == list(range(len(samples)))
    gaps = {b.micros - a.micros for a, b in itertools.pairwise(samples)}
    assert min(gaps) >= 9_500 and max(gaps) <= 10_500
    assert _ask(emu, "2 STREAM 0", 10.0) == "OK 2 STREAM"
    assert emu.poll(10.1) == b""


def test_stream_never_faster_than_rate_with_coarse_polls():
    emu = StepperBoardEmulator(SimpleStepperHardware())
    emu.poll(0.0)
    _ask(emu, "1 STREAM 200")
    lines = sum(emu.poll(0.05 * k).count(b"\n") for k in range(1, 41))  # 2 s polled at 20 Hz
    assert lines == 40


def test_stepper_emulator_move():
    emu = StepperBoardEmulator(SimpleStepperHardware())
    assert _ask(emu, "1 SPEED 1000 5000") == "OK 1 SPEED"
    assert _ask(emu, "2 MOVE 500") == "OK 2 MOVE"
    pos = bp.parse_message(_ask(emu, "3 POS?", 0.25))
    assert isinstance(pos, bp.Position) and pos.moving and 240 <= pos.position_steps <= 260
    pos = bp.parse_message(_ask(emu, "4 POS?", 1.0))
    assert pos.position_steps == 500 and not pos.moving
    assert _ask(emu, "5 SPEED 0 5000") == "ERR 5 5 RANGE"


# ------------------------------------------------------------------------------- drivers over a pty
def _until(predicate, timeout_s: float = 3.0, every_s: float = 0.02):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if result := predicate():
            return result
        time.sleep(every_s)
    raise AssertionError("condition not met in time")


def test_pressure_board_streams_towards_the_set_point(host_factory):
    with host_factory(PRESSURE) as ports, PressureBoard(ports["pressure_board"]) as board:
        assert board.identity.board == "PRESSURE"
        board.start_stream(100)
        board.set_pressure(0, 200_000.0)
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.5:
            samples += board.read_samples()
            time.sleep(0.01)
        board.stop_stream()
        with pytest.raises(DeviceReplyError, match=r"pressure board on .*RANGE"):
            board.set_pressure(1, 900_000.0)
    assert 120 <= len(samples) <= 160
    seqs = [s.seq for s in samples]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    target = round((0.5 + 4.0 * 200_000 / 400_000) / bp.ADC_LSB_V)  # 2.5 V → 20000 counts
    assert abs(samples[-1].counts[0] - target) < 40
    assert abs(samples[-1].counts[1] - 4000) < 40  # channel 1 stays at 0 Pa (0.5 V)
    # the board clock runs at 1 + 1500 ppm of host time; 10 ms read jitter over 1.5 s only resolves ±1 %
    first, last = samples[0], samples[-1]
    rate = (last.micros - first.micros) * 1e3 / (last.host_ns - first.host_ns)
    assert 0.98 < rate < 1.02
    assert all(b.micros > a.micros for a, b in itertools.pairwise(samples))


def test_stepper_board_move_reaches_target(host_factory):
    with host_factory(STEPPER) as ports, StepperBoard(ports["stepper_board"]) as board:
        assert board.identity.board == "STEPPER"
        board.set_speed(4000, 20000)
        board.start_stream(50)
        board.move_to(1600)
        final = _until(lambda: (p := board.position()).position_steps == 1600 and not p.moving and p)
        assert final.seq is None and final.host_ns > 0
        streamed = board.read_samples()
        board.stop_stream()
    assert streamed and all(s.seq is not None for s in streamed)
    assert [s.position_steps for s in streamed] == sorted(s.position_steps for s in streamed)


def test_wrong_board_on_the_port_is_not_found(host_factory):
    with host_factory(STEPPER) as ports:
        with pytest.raises(DeviceNotFoundError, match="not a PRESSURE board"):
            PressureBoard(ports["stepper_board"]).open()


def test_missing_port_raises_not_found_naming_the_path(tmp_path):
    path = str(tmp_path / "ttyACM-nothing")
    with pytest.raises(DeviceNotFoundError, match=re.escape(path)):
        with PressureBoard(path):
            pass
