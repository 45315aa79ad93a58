"""The Arduino boards: line codec, PROTOCOL.md examples, emulators byte for byte, the reset a port open
causes (DTR), drivers over a real pty and their error messages. The vector table against emulator and
firmware is tests/test_board_vectors.py."""

from __future__ import annotations

import itertools
import re
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from acquisition.codecs import board_lines as bp
from acquisition.devices.boards import BoardReplyError, PressureBoard, StepperBoard
from acquisition.errors import DeviceError, DeviceNotFoundError, DeviceProtocolError, DeviceReplyError
from twin.emulators.board_firmware import CATCH_UP_S, PressureBoardEmulator, StepperBoardEmulator
from twin.emulators.board_hardware import SimplePressureHardware, SimpleStepperHardware

PROTOCOL_MD = Path(__file__).resolve().parents[1] / "firmware" / "PROTOCOL.md"
PRESSURE = "pressure_board=twin.emulators.board_firmware:demo_pressure_board"
STEPPER = "stepper_board=twin.emulators.board_firmware:demo_stepper_board"


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


@pytest.mark.parametrize(
    "bad",
    [b"OK 1 SET\n", b"OK 1 SET*7\n", b"OK 1 SET*ZZ\n", b"x" * 80 + b"*00\n", b"OK 1 SET* 3\n",
     b"OK 1 SET*+3\n", bp.encode("OK 1 SET")[:-1] + b"\r\r\n", b"OK 1\tSET*00\n"],
)  # fmt: skip
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


def test_decode_accepts_one_cr_and_lowercase_digits():
    line = bp.encode("8 SET 0 150000")
    assert line.endswith(b"*6E\n")
    assert bp.decode(line.replace(b"*6E", b"*6e")) == "8 SET 0 150000"
    assert bp.decode(line[:-1] + b"\r\n") == "8 SET 0 150000"


def test_parse_tag_follows_the_firmware():
    assert bp.parse_tag("00042") == 42 and bp.parse_tag("65535") == 65535
    for bad in ("123456", "65536", "-1", "x", "", "٣"):
        with pytest.raises(bp.BoardSyntaxError):
            bp.parse_tag(bad)


# --------------------------------------------------------------------------------------- emulators
def _ask(emulator, body: str, now_s: float = 0.0) -> str:
    reply = emulator.feed(bp.encode(body), now_s)
    assert reply.count(b"\n") == 1
    return bp.decode(reply)


def _powered(emulator):
    """An emulator after power-up, its READY taken."""
    assert bp.parse_message(bp.decode(emulator.poll(0.0))) == bp.Ready(emulator.board, "1.0.0")
    return emulator


def test_ready_comes_before_any_reply():
    emu = PressureBoardEmulator(SimplePressureHardware())
    out = emu.feed(bp.encode("1 ID?"), 0.0)
    assert [bp.decode(line + b"\n").split()[0] for line in out.splitlines()] == ["READY", "ID"]


def test_pressure_emulator_commands():
    emu = _powered(PressureBoardEmulator(SimplePressureHardware()))
    assert _ask(emu, "1 ID?") == "ID 1 PRESSURE 1.0.0 VSLP-0001"
    assert _ask(emu, "2 SET 0 150000") == "OK 2 SET"
    assert emu.hw.setpoint_pa[0] == 150000.0
    assert _ask(emu, "3 VALVE 1 1") == "OK 3 VALVE" and emu.valves == 2
    assert _ask(emu, "4 SET 0 500000") == "ERR 4 5 RANGE"
    assert _ask(emu, "4 SET 1 350000") == "ERR 4 5 RANGE", "above the regulators' 3 bar"
    assert _ask(emu, "4 SET 1 -1") == "ERR 4 5 RANGE"
    assert emu.hw.setpoint_pa == [150000.0, 0.0], "a refused set-point changes nothing"
    assert _ask(emu, "4 SET 1 300000") == "OK 4 SET" and emu.hw.setpoint_pa[1] == 300000.0
    assert _ask(emu, "5 SET 0 abc") == "ERR 5 4 ARGS"
    assert _ask(emu, "6 MOVE 10") == "ERR 6 3 UNKNOWN"
    assert _ask(emu, "7 STOP") == "OK 7 STOP" and emu.valves == 0 and emu.hw.setpoint_pa == [0.0, 0.0]


def test_pressure_emulator_limit_is_the_firmwares_unless_told():
    emu = _powered(PressureBoardEmulator(SimplePressureHardware(), max_set_pa=100_000))
    assert _ask(emu, "1 SET 0 100001") == "ERR 1 5 RANGE"
    assert _ask(emu, "2 SET 0 100000") == "OK 2 SET"


def test_bad_checksum_and_split_input():
    emu = _powered(PressureBoardEmulator(SimplePressureHardware()))
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


def test_stream_at_its_rate_however_coarsely_the_rig_polls():
    """The board's loop is not late when the rig is: polled at 20 Hz, a 200 Hz stream gives every sample,
    each stamped with the micros() it was due at, never more (one line a period)."""
    emu = StepperBoardEmulator(SimpleStepperHardware())
    emu.poll(0.0)
    _ask(emu, "1 STREAM 200")
    lines = [bp.parse_message(bp.decode(line + b"\n")) for k in range(1, 41)  # 2 s polled at 20 Hz
             for line in emu.poll(0.05 * k).splitlines()]  # fmt: skip
    assert len(lines) == 401  # the first at the STREAM, then one every 5 ms to 2 s
    assert [m.seq for m in lines] == list(range(401))
    assert set(np.diff([m.micros for m in lines]).tolist()) == {5000}


def test_a_rig_stopped_longer_than_its_recent_steps_skips_the_samples_older_than_that():
    emu = StepperBoardEmulator(SimpleStepperHardware())
    emu.poll(0.0)
    _ask(emu, "1 STREAM 100")
    emu.poll(0.0)
    lines = emu.poll(1.0).splitlines()  # the samples of the last CATCH_UP_S come, numbered on
    assert len(lines) - round(CATCH_UP_S * 100) in (0, 1) and emu.seq == len(lines) + 1  # (the edge's sample)


def test_stepper_emulator_move():
    emu = _powered(StepperBoardEmulator(SimpleStepperHardware()))
    assert _ask(emu, "1 SPEED 1000 5000") == "OK 1 SPEED"
    assert _ask(emu, "2 MOVE 500") == "OK 2 MOVE"
    pos = bp.parse_message(_ask(emu, "3 POS?", 0.25))
    assert isinstance(pos, bp.Position) and pos.moving and 240 <= pos.position_steps <= 260
    pos = bp.parse_message(_ask(emu, "4 POS?", 1.0))
    assert pos.position_steps == 500 and not pos.moving
    assert _ask(emu, "5 SPEED 0 5000") == "ERR 5 5 RANGE"


# ---------------------------------------------------------------------------- reset on open (DTR), no pty
def test_a_port_open_resets_the_pressure_board():
    hw = SimplePressureHardware(drift_ppm=0.0, offset_s=500.0)
    emu = _powered(PressureBoardEmulator(hw))
    _ask(emu, "1 SET 0 200000", 1.0)
    _ask(emu, "2 VALVE 1 1", 1.0)
    _ask(emu, "3 STREAM 100", 1.0)
    assert bp.parse_message(bp.decode(emu.poll(1.0))).seq == 0
    caught_up = round(CATCH_UP_S * 100) + 1  # not polled for 0.5 s: the samples of the last CATCH_UP_S
    assert len(emu.poll(1.5).splitlines()) == caught_up and emu.seq == 1 + caught_up
    emu.port_opened(2.0)
    assert emu.resets == 1 and emu.booting(2.0) and emu.booting(2.0 + bp.BOOT_S - 1e-6)
    assert hw.setpoint_pa == [0.0, 0.0] and hw.valve_open == [False, False], "outputs fall at once"
    assert emu.feed(bp.encode("4 ID?"), 2.5) == b"", "the bootloader swallows what the host sends"
    assert emu.feed(b"9 I", 2.9) == b"", "half a line, lost too"
    assert emu.poll(2.5) == b"" and emu.next_output_s(2.5) == pytest.approx(2.0 + bp.BOOT_S)
    ready = emu.poll(2.0 + bp.BOOT_S)
    assert bp.parse_message(bp.decode(ready)) == bp.Ready("PRESSURE", "1.0.0")
    assert emu.next_output_s(4.0) is None, "streaming is off after the reset"
    assert _ask(emu, "5 ID?", 4.0).startswith("ID 5 PRESSURE")
    _ask(emu, "6 STREAM 100", 4.0)
    first = bp.parse_message(bp.decode(emu.poll(4.0)))
    assert first.seq == 0 and first.valves == 0, "seq restarts, valves released"
    since_sketch_us = (4.0 - 2.0 - bp.BOOT_S) * 1e6
    assert first.micros == pytest.approx(since_sketch_us, abs=2), "micros() counts from the sketch's start"


def test_a_port_open_resets_the_stepper_count_where_the_motor_stands():
    emu = _powered(StepperBoardEmulator(SimpleStepperHardware(drift_ppm=0.0)))
    _ask(emu, "1 SPEED 4000 8000", 0.0)
    _ask(emu, "2 MOVE 4000", 0.0)
    emu.port_opened(0.5)  # the motor has made 2000 microsteps
    assert emu.hw.target == 2000 and emu.zero == 2000, "no step pulses during the reset"
    assert emu.hw.speed_steps_s == 1000.0, "setup()'s speed"
    emu.poll(0.5 + bp.BOOT_S)
    pos = bp.parse_message(_ask(emu, "3 POS?", 2.0))
    assert pos.position_steps == 0 and not pos.moving
    _ask(emu, "4 MOVE 100", 2.0)
    pos = bp.parse_message(_ask(emu, "5 POS?", 3.0))
    assert pos.position_steps == 100 and emu.hw.position(3.0) == 2100, "targets count from the reset"


def test_a_replug_restarts_the_sketch():
    emu = _powered(PressureBoardEmulator(SimplePressureHardware()))
    _ask(emu, "1 STREAM 100", 0.0)
    emu.feed(b"1 ID", 0.0)
    emu.reset_link()
    assert emu.stream_hz == 0 and emu.next_output_s(1.0) == 1.0, "READY due again"
    assert bp.decode(emu.poll(1.0)).startswith("READY")
    assert _ask(emu, "2 ID?", 1.0).startswith("ID 2 "), "the half line before the replug is gone"


# ------------------------------------------------------------------------------- drivers over a pty
def _until(predicate, timeout_s: float = 3.0, every_s: float = 0.02):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if result := predicate():
            return result
        time.sleep(every_s)
    raise AssertionError("condition not met in time")


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_wrong_board_on_the_port_is_not_found(host_factory):
    with host_factory(STEPPER) as ports:
        with pytest.raises(DeviceNotFoundError, match="not a PRESSURE board"):
            PressureBoard(ports["stepper_board"]).open()


def test_missing_port_raises_not_found_naming_the_path(tmp_path):
    path = str(tmp_path / "ttyACM-nothing")
    with pytest.raises(DeviceNotFoundError, match=re.escape(path)):
        with PressureBoard(path):
            pass


# ------------------------------------------------------------------------ reopen and errors over a pty
def _read_for(port: serial.Serial, seconds: float) -> list[tuple[float, bytes]]:
    """Lines (with their arrival time after the call) read from ``port`` for ``seconds``."""
    t0, buf, lines = time.monotonic(), b"", []
    while time.monotonic() - t0 < seconds:
        buf += port.read(4096)
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            lines.append((time.monotonic() - t0, line + b"\n"))
    return lines


@pytest.mark.slow
def test_reopening_the_port_resets_the_board_like_an_uno(host_factory):
    with host_factory(PRESSURE) as ports:
        path = ports["pressure_board"]
        t0 = time.monotonic()
        with PressureBoard(path) as board:
            open_s = time.monotonic() - t0
            board.set_valve(1, True)
            board.set_pressure(0, 200_000.0)
            board.start_stream(100)
            time.sleep(0.5)
            before = board.read_samples()
        assert bp.BOOT_S - 0.05 < open_s < bp.BOOT_S + 0.6, f"open() waits for READY ({open_s:.2f} s)"
        assert before[-1].valves == 2 and abs(before[-1].counts[0] - 20_000) < 40  # 2 bar

        with serial.Serial(path, bp.BAUD, timeout=0.02) as raw:  # the port left streaming at 100 Hz
            raw.write(bp.encode("1 ID?"))  # during the bootloader: lost
            lines = _read_for(raw, bp.BOOT_S + 0.6)
        ready = [t for t, line in lines if line == bp.encode("READY PRESSURE 1.0.0")]
        assert len(ready) == 1 and bp.BOOT_S - 0.05 < ready[0] < bp.BOOT_S + 0.3, lines
        assert all(t < 0.05 for t, line in lines if t < ready[0]), "before READY only lines already in flight"
        assert [line for t, line in lines if t > ready[0]] == [], "no reply to ID?, no stream after the reset"

        with PressureBoard(path) as board:
            board.start_stream(100)
            time.sleep(0.3)
            after = board.read_samples()
    assert after[0].seq == 0, "seq restarts at 0"
    assert after[0].micros < (bp.BOOT_S + 1.0) * 1e6, "micros() restarts with the sketch"
    assert after[-1].valves == 0 and abs(after[-1].counts[0] - 4000) < 40, "valves released, 0 Pa"


@pytest.mark.slow
def test_driver_errors_name_the_board_the_command_and_the_reply(host_factory):
    with host_factory(PRESSURE) as ports, PressureBoard(ports["pressure_board"]) as board:
        path = ports["pressure_board"]
        with pytest.raises(BoardReplyError) as info:
            board.set_pressure(1, 350_000.0)
        err = info.value
        assert isinstance(err, DeviceReplyError) and isinstance(err, DeviceError)
        assert (err.board, err.port, err.command, err.code, err.name) == ("PRESSURE", path, "SET 1 350000", 5,
                                                                          "RANGE")  # fmt: skip
        assert str(err).startswith(f"pressure board on {path} refused 'SET 1 350000': ERR 5 RANGE: ")
        assert "nothing was applied" in str(err) and "SET <channel 0–1> <pa 0–300000>" in str(err)
        with pytest.raises(BoardReplyError, match=r"'SET 0 -1000': ERR 5 RANGE"):
            board.set_pressure(0, -1000.0)
        with pytest.raises(BoardReplyError, match=r"'SET 0': ERR 4 ARGS: wrong number.*usage: SET"):
            board.command("SET 0")
        with pytest.raises(BoardReplyError, match=r"'FLY': ERR 3 UNKNOWN: the board has no such command$"):
            board.command("FLY")
        with pytest.raises(BoardReplyError, match=r"MOVE is a STEPPER board command: is this the right port"):
            board.command("MOVE 5")
        write = board._write
        board._write = lambda data: write(data[:-3] + b"%02X\n" % (int(data[-3:-1], 16) ^ 1))
        with pytest.raises(DeviceProtocolError, match=r"could not read 'STOP': ERR 1 CHECKSUM.*3 attempts"):
            board.stop()
        board._write = write
        board.stop()  # the board is fine
