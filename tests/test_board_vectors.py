"""One table of the boards' test vectors (firmware/vectors.json), run byte for byte against the emulators and
against the sketches themselves compiled for the host with g++ (firmware/test/host: the Arduino hardware is
stood in for, VslLink and the sketches' command handlers are the real code); then random lines through both,
which must agree on every byte."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from acquisition.codecs import board_lines as bp
from twin.emulators.board_firmware import PressureBoardEmulator, StepperBoardEmulator
from twin.emulators.board_hardware import SimplePressureHardware, SimpleStepperHardware

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"
TABLE = json.loads((FIRMWARE / "vectors.json").read_text(encoding="utf-8"))
BOARDS = {bp.BOARD_PRESSURE: "pressure_board", bp.BOARD_STEPPER: "stepper_board"}
VERBS = {
    bp.BOARD_PRESSURE: {"ID?", "STREAM", "STOP", "SET", "VALVE"},
    bp.BOARD_STEPPER: {"ID?", "STREAM", "STOP", "MOVE", "SPEED", "POS?"},
}


def _bytes(text: str) -> bytes:
    return text.encode("latin-1")


def vectors(board: str) -> list[tuple[bytes, bytes, str]]:
    """(send, reply, why) of ``board``, in the table's order."""
    rows = [v for v in TABLE["vectors"] if v["board"] in ("both", board)]
    return [(_bytes(v["send"]), _bytes(v["reply"]), v["why"]) for v in rows]


# ------------------------------------------------------------------------------------ the two boards
class _FrozenPressure(SimplePressureHardware):
    """The pressure hardware with micros() frozen at the table's value (as the host harness freezes it)."""

    def micros(self, now_s: float) -> int:
        return TABLE["micros"]


class _FrozenStepper(SimpleStepperHardware):
    def micros(self, now_s: float) -> int:
        return TABLE["micros"]


def emulator_session(board: str, chunks: list[bytes]) -> tuple[bytes, list[bytes]]:
    """The emulator at power-up: its READY, then what it answers to each chunk (no time passes)."""
    emu = (
        PressureBoardEmulator(_FrozenPressure())
        if board == bp.BOARD_PRESSURE
        else StepperBoardEmulator(_FrozenStepper())
    )
    ready = emu.poll(0.0)
    return ready, [emu.feed(chunk, 0.0) for chunk in chunks]


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    """Build the host harness of each sketch with g++; ``harness(board, chunks)`` runs one session."""
    gxx = shutil.which("g++")
    if gxx is None:
        pytest.skip("g++ is not installed: the sketches cannot be compiled for the host (apt install g++)")
    out_dir = tmp_path_factory.mktemp("firmware")
    binaries = {}
    host, link = FIRMWARE / "test" / "host", FIRMWARE / "libraries" / "VslLink" / "src"
    for board, sketch in BOARDS.items():
        binary = out_dir / sketch
        cmd = [gxx, "-std=c++17", "-O1", "-Wall", "-Wextra", f"-DVSL_MOCK_MICROS={TABLE['micros']}UL",
               f"-I{host}", f"-I{link}", f"-I{FIRMWARE / sketch}", f'-DSKETCH="{sketch}.ino"',
               str(host / "harness.cpp"), str(link / "VslLink.cpp"), "-o", str(binary)]  # fmt: skip
        built = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert built.returncode == 0, f"{sketch} does not compile for the host:\n{built.stderr}"
        binaries[board] = binary

    def run(board: str, chunks: list[bytes]) -> tuple[bytes, list[bytes]]:
        stdin = "".join(chunk.hex() + "\n" for chunk in chunks)
        done = subprocess.run([binaries[board]], input=stdin, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        lines = done.stdout.splitlines()
        assert len(lines) == len(chunks) + 1, "one output line per input line, after setup()'s"
        return bytes.fromhex(lines[0]), [bytes.fromhex(line) for line in lines[1:]]

    return run


# ------------------------------------------------------------------------------------------- the table
def test_the_table_covers_every_command_error_and_limit():
    for board in BOARDS:
        rows = vectors(board)
        sent = [
            bp.frame_error(send.rstrip(b"\n")) == 0 and bp.split_fields(bp.decode(send))
            for send, _, _ in rows
        ]
        verbs = {fields[1] for fields in sent if fields and len(fields) > 1}
        assert verbs >= VERBS[board], f"{board}: a command without a vector"
        codes = Counter(bp.parse_message(bp.decode(line + b"\n")).code for _, reply, _ in rows
                        for line in reply.splitlines() if line.startswith(b"ERR"))  # fmt: skip
        assert set(codes) == set(bp.ERROR_NAMES), f"{board}: an error reply without a vector ({codes})"
        assert all(why for _, _, why in rows), "every vector says what it checks"
    sends = {v["send"] for v in TABLE["vectors"]}
    wanted = {bp.encode(body).decode() for body in ("8 SET 1 350000", "8 SET 0 -1", "8 SET 2 1000")}
    assert wanted <= sends, "above 3 bar, negative, no such channel"
    assert any(len(s) > bp.MAX_BODY + 5 for s in sends), "an overlong line"


def test_the_table_agrees_with_the_protocol_limits():
    top = bp.encode(f"8 SET 1 {bp.MAX_SET_PA}").decode()
    assert any(v["send"] == top and v["reply"].startswith("OK ") for v in TABLE["vectors"]), (
        "the top accepted"
    )
    text = (FIRMWARE / "PROTOCOL.md").read_text()
    assert f"0–{bp.MAX_SET_PA:,}".replace(",", " ") in text, "PROTOCOL.md states the set-point limit"
    sketch = (FIRMWARE / "pressure_board" / "pressure_board.ino").read_text()
    assert f"MAX_SET_PA = {bp.MAX_SET_PA}L" in sketch, "the sketch and the Python constant in step"


@pytest.mark.parametrize("board", list(BOARDS))
def test_the_emulator_answers_every_vector(board):
    rows = vectors(board)
    ready, replies = emulator_session(board, [send for send, _, _ in rows])
    assert ready == _bytes(TABLE["ready"][board])
    wrong = [
        (why, send, want, got) for (send, want, why), got in zip(rows, replies, strict=True) if got != want
    ]
    assert not wrong, "\n".join(
        f"{why}: {send!r} → {got!r}, the table says {want!r}" for why, send, want, got in wrong
    )


@pytest.mark.parametrize("board", list(BOARDS))
def test_the_firmware_answers_every_vector(board, harness):
    rows = vectors(board)
    ready, replies = harness(board, [send for send, _, _ in rows])
    assert ready == _bytes(TABLE["ready"][board])
    wrong = [
        (why, send, want, got) for (send, want, why), got in zip(rows, replies, strict=True) if got != want
    ]
    assert not wrong, "\n".join(
        f"{why}: {send!r} → {got!r}, the table says {want!r}" for why, send, want, got in wrong
    )


# ------------------------------------------------------------------------------------ differential run
ARITY = {"ID?": 0, "STREAM": 1, "STOP": 0, "SET": 2, "VALVE": 2, "MOVE": 1, "SPEED": 2, "POS?": 0, "FLY": 1}


def random_chunks(n: int, seed: int) -> list[bytes]:
    """Lines near the protocol (real verbs, mostly with their arity, arguments around their limits; odd tags,
    wrong or lowercase checksums, CRs, a stray byte) and raw byte soup (partial lines, NULs, overlong
    runs), from a seeded generator."""
    rng = np.random.default_rng(seed)
    odd = ["+5", "-0", "1x", "00000000001", "99999999999", "+", "-", "1.5", "0x10", "300000", "300001"]
    around = [0, 1, 2, 250, 251, 4000, 4001, 100_000, 100_001, 300_000, 300_001, 2_000_000, 2_000_001]

    def arg() -> str:
        kind = rng.integers(0, 5)
        if kind == 0:
            return str(rng.integers(-2, 3))
        if kind == 1:
            return str(int(rng.choice(around)) * int(rng.choice([1, 1, 1, -1])))
        if kind == 2:
            return str(rng.choice(odd))
        return str(rng.integers(0, 400_001))

    chunks = []
    for _ in range(n):
        kind = rng.integers(0, 20)
        if kind < 17:
            verb = str(rng.choice(list(ARITY)))
            nargs = ARITY[verb] if rng.integers(0, 4) else int(rng.integers(0, 6))
            tag = (
                str(rng.integers(0, 65_536))
                if kind < 14
                else str(rng.choice(["007", "000001", "65536", "-", "a1"]))
            )
            raw = " ".join([tag, verb, *(arg() for _ in range(nargs))]).encode()
            cs = bp.checksum(raw)
            line = raw + b"*%02X" % cs
            if kind >= 12:  # a flaw in the framing
                flaws = [b"*%02x" % cs, b"*%02X" % (cs ^ 0x10), b"*%02X\r" % cs, b"", b"*%02X\r\r" % cs]
                line = raw.replace(b" ", b"  ", 1) + b"*%02X" % cs if kind == 19 else raw + flaws[kind % 5]
                if rng.integers(0, 3) == 0:
                    at = rng.integers(0, len(line) + 1)
                    line = line[:at] + bytes([rng.integers(0, 256)]) + line[at:]
            chunks.append(line + b"\n")
        else:
            soup = np.frombuffer(b"0123456789 *\r\nABCDEFabcdef?SETVALVE\x00\xff\t", dtype=np.uint8)
            chunks.append(
                bytes(rng.choice(soup, rng.integers(0, 90))) + (b"\n" if rng.integers(0, 8) else b"")
            )
    return chunks


@pytest.mark.parametrize("board", list(BOARDS))
def test_emulator_and_firmware_agree_on_random_lines(board, harness):
    chunks = random_chunks(4000, seed=14)
    fw_ready, fw = harness(board, chunks)
    emu_ready, emu = emulator_session(board, chunks)
    assert emu_ready == fw_ready
    differ = [(c, f, e) for c, f, e in zip(chunks, fw, emu, strict=True) if f != e]
    assert not differ, "\n".join(f"{c!r}: firmware {f!r}, emulator {e!r}" for c, f, e in differ[:10])
    replies = Counter(line.split(b" ")[0] + (b" " + line.split(b" ")[2] if line.startswith(b"ERR") else b"")
                      for out in fw for line in out.splitlines())  # fmt: skip
    for code in bp.ERROR_NAMES:  # the run reached every error and plenty of successes
        assert replies[b"ERR %d" % code] > 20, (code, replies)
    assert sum(n for kind, n in replies.items() if not kind.startswith(b"ERR")) > 100, replies
