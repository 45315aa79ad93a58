"""A lab's own device kind, outside the project: a serial load cell under the arm's payload hook.

One module holds all of it (codec, driver, emulator, recording source, twin stream and rows) and one line
registers it (an entry point ``loadcell = "loadcell:KIND"`` in the ``vslab.device_kinds`` group, or
``driver: loadcell:KIND`` in the robot description); no file of vslab is edited. The tests use it to show
that a new kind is recorded on the rig and simulated like the built-in ones.

Wire protocol (ASCII lines, 115200 baud): the host sends ``R\\n``; the cell answers
``S <seq> <micros> <counts>*<XX>\\n``, ``XX`` the two hex digits of the XOR of the bytes before ``*``.
"""

from __future__ import annotations

import numpy as np
import serial

from acquisition.devices.base import Device, host_now_ns
from acquisition.devices.kinds import DeviceKind
from acquisition.errors import CodecError, DeviceProtocolError, DeviceTimeoutError
from acquisition.recorder.source_base import SEQ_MODULO, Row, Source
from acquisition.schemas.cdr import Field, FixedMessage
from twin import streams as twin_streams
from twin.emulators.base import Emulator

TOPIC = "/loadcell/force"
NEWTON_PER_COUNT = 0.001  # 1 mN a count
NOISE_COUNTS = 2.0  # the cell's noise (counts, rms)
MESSAGE = FixedMessage(
    "lab_msgs/msg/LoadCell",
    (
        Field("seq", "uint32", doc="the cell's sample number"),
        Field("micros", "uint32", doc="the cell's micros(), wraps at 2^32"),
        Field("counts", "int32", doc="ADC counts"),
        Field("force", "float64", doc="N, along gravity"),
    ),
    "The load on the arm's payload hook.",
)


# ------------------------------------------------------------------------------------------------ codec
def _checksum(body: bytes) -> bytes:
    x = 0
    for b in body:
        x ^= b
    return f"{x:02X}".encode()


def encode_sample(seq: int, micros: int, counts: int) -> bytes:
    body = f"S {seq} {micros} {counts}".encode()
    return body + b"*" + _checksum(body) + b"\n"


def decode_sample(line: bytes) -> tuple[int, int, int]:
    """(seq, micros, counts) of one sample line; a malformed line or a bad checksum is a CodecError."""
    body, star, check = line.strip().partition(b"*")
    parts = body.split()
    if not star or check != _checksum(body) or len(parts) != 4 or parts[0] != b"S":
        raise CodecError(f"load cell: bad sample line {line!r}")
    return int(parts[1]), int(parts[2]), int(parts[3])


def row_values(seq: int | np.ndarray, micros, counts) -> dict:
    """The message's fields from what the cell sends: the ONE place its rows are made, for the recorder
    (one sample) and the simulated runner (a window of them)."""
    counts = np.asarray(counts)
    return {"seq": np.asarray(seq) % SEQ_MODULO, "micros": micros, "counts": counts,
            "force": counts * NEWTON_PER_COUNT}  # fmt: skip


# ----------------------------------------------------------------------------------------------- driver
class LoadCell(Device):
    """The load cell on a serial port: ``read()`` asks for one sample."""

    kind = "load cell"

    def __init__(self, port: str, baud: int = 115200, timeout_s: float = 0.1) -> None:
        super().__init__(port)
        self.baud, self.timeout_s = baud, timeout_s
        self._ser: serial.Serial | None = None

    def _open(self) -> None:
        self._ser = serial.Serial(self.port, self.baud, timeout=self.timeout_s)
        self.read()  # it answers, or the open fails

    def _close(self) -> None:
        if self._ser is not None:
            self._ser.close()
            self._ser = None

    def read(self) -> tuple[int, int, int, int]:
        """(host receive time ns, seq, micros, counts) of one fresh sample."""

        def attempt() -> tuple[int, int, int, int]:
            self._ser.reset_input_buffer()
            self._ser.write(b"R\n")
            line = self._ser.readline()
            host_ns = host_now_ns()
            if not line.endswith(b"\n"):
                raise DeviceTimeoutError("no answer")
            try:
                return (host_ns, *decode_sample(line))
            except CodecError as exc:
                raise DeviceProtocolError(str(exc)) from exc

        return self._retrying("R", attempt)


# ----------------------------------------------------------------------------------------------- source
class LoadCellSource(Source):
    """Polled at the device's rate; numbered by the cell's own sample counter."""

    driver = "loadcell"
    sampled_topics = (TOPIC,)

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.cell = LoadCell(port, baud=spec.baud)
        self.last: int | None = None

    def open(self) -> None:
        self.cell.open()

    def close(self) -> None:
        self.cell.close()

    def read(self, slot: int) -> list[Row]:
        host_ns, seq, micros, counts = self.cell.read()
        return [self.row(TOPIC, host_ns, seq % SEQ_MODULO, **row_values(seq, micros, counts))]


# --------------------------------------------------------------------------------------------- emulator
class LoadCellEmulator(Emulator):
    """The cell on the twin: the payload's weight, on its own clock and with its own noise."""

    name = "loadcell"

    def __init__(self, rig, device: str) -> None:
        self.rig, self.device = rig, device
        self.rng = rig.world.device_rng(device)
        self.seq = 0
        self._line = b""

    def feed(self, data: bytes, now_s: float) -> bytes:
        self._line += data
        out = b""
        while b"\n" in self._line:
            cmd, self._line = self._line.split(b"\n", 1)
            if cmd.strip() == b"R":
                self.rig.advance(now_s)
                out += encode_sample(self.seq, self.rig.ticks(self.device), self._counts())
                self.seq += 1
        return out

    def _counts(self) -> int:
        payload = float(self.rig.world.commands.payload_kg[0])
        g = -float(self.rig.robot.gravity_m_s2[2])
        return round(payload * g / NEWTON_PER_COUNT + float(self.rng.normal(0.0, NOISE_COUNTS)))


def emulator(rig, name: str, spec) -> Emulator:
    return LoadCellEmulator(rig, name)


# --------------------------------------------------------------------------------------- twin stream
def stream(world, name: str, trace, servo_rate_hz: float) -> dict:
    """What the cell reports during ``trace`` when the host polls it at its rate (simulated time)."""
    rate = world.robot.devices[name].rate_hz
    r, k, t = twin_streams.host_poll_instants(
        trace.q.shape[0], 1.0 / rate, trace.t[0] - world.dt, trace.t[-1]
    )
    rng = world.device_rng(name)
    g = -float(world.robot.gravity_m_s2[2])
    force = world.commands.payload_kg[r] * g
    counts = np.rint(force / NEWTON_PER_COUNT + rng.normal(0.0, NOISE_COUNTS, len(r))).astype(np.int64)
    spec = world.robot.devices[name]
    return {name: {"robot": r, "seq": k, "t_true": t,
                   "host_ns": twin_streams._host(spec.host_link, t, rng),
                   "micros": world.clocks[name].ticks_at(r, t), "counts": counts}}  # fmt: skip


def rows(robot, name: str, topics, streams, valve_open) -> dict:
    s = streams.get(name)
    if s is None or TOPIC not in topics:
        return {}
    data = topics[TOPIC].message.pack(row_values(s["seq"], s["micros"], s["counts"]))
    return {TOPIC: (s["robot"], s["host_ns"], data)}


KIND = DeviceKind(
    name="loadcell",
    source="loadcell:LoadCellSource",
    topics=lambda robot, name: {TOPIC: MESSAGE},
    stamps={TOPIC: "micros"},
    emulator="loadcell:emulator",
    streams=((100, "loadcell:stream"),),
    rows=((100, "loadcell:rows"),),
)
