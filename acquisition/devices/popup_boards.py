"""POPUP's main board and link boards, read and commanded on the CAN bus the joint drives share.

The boards' frames are those of ``configs/can/popup_boards.dbc`` (``acquisition.codecs.popup_boards``,
cantools). :class:`BoardFrames` subscribes to them on the drives' canopen ``Network`` (one adapter, one
bus), stamps each on arrival, decodes it and unwraps its 16-bit sample counter into a sample number, so a
lost frame is a gap in the numbers. It sends the main board's ``PressureCommand`` (set-points and which links
it regulates) and notices a board whose frames stopped (:class:`BoardLostError`).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import canopen

from acquisition.codecs import popup_boards as pb
from acquisition.devices.base import host_now_ns
from acquisition.errors import CodecError, DeviceDisconnectedError

SILENT_PERIODS = 10  # periods of a board's slowest stream without a frame before it counts as lost
MIN_SILENT_S = 0.3


class BoardLostError(DeviceDisconnectedError):
    """A board's frames stopped (power, cable)."""


@dataclass(frozen=True)
class BoardSample:
    """One board frame as received: its message, host receive time, sample number (the unwrapped counter)
    and physical signal values."""

    message: str
    host_ns: int
    seq: int
    signals: dict[str, float]


class _Counter:
    """A frame counter of ``modulo`` values unwrapped into a growing sample number."""

    def __init__(self, modulo: int) -> None:
        self.modulo, self.last, self.seq = modulo, None, 0

    def number(self, counter: int) -> int:
        if self.last is not None:
            self.seq += (counter - self.last) % self.modulo or self.modulo  # a repeat: a whole wrap lost
        else:
            self.seq = counter
        self.last = counter
        return self.seq


class BoardFrames:
    """The frames of the boards ``nodes`` (device name → node id) on a canopen network; ``periods_s``
    (device name → its slowest stream's period) says how long a board may stay silent."""

    def __init__(self, nodes: dict[str, int], periods_s: dict[str, float]) -> None:
        self.nodes = dict(nodes)
        self.limit_s = {n: max(SILENT_PERIODS * periods_s[n], MIN_SILENT_S) for n in nodes}
        device_of_node = {node: n for n, node in self.nodes.items()}
        # can id → (message, device) of every frame these boards send (the host's command is not one)
        sent = [m for m in pb.database().messages if pb.HOST not in m.senders]
        self.board_of = {m.frame_id: (m.name, device_of_node[pb.node_of(m.frame_id)])
                         for m in sent if pb.node_of(m.frame_id) in device_of_node}  # fmt: skip
        self.network: canopen.Network | None = None
        self._lock = threading.Lock()
        self._frames: list[tuple[int, int, bytes]] = []
        self._counters: dict[int, _Counter] = {}
        self._last_heard: dict[str, float] = {}
        self._command_counter = 0
        self.undecodable = 0

    def attach(self, network: canopen.Network) -> None:
        """Listen on ``network`` (the drives' bus): every board frame is queued from now on."""
        self.network = network
        now = time.monotonic()
        self._last_heard = {n: now for n in self.nodes}
        for can_id in self.board_of:
            network.subscribe(can_id, self._on_frame)

    def detach(self) -> None:
        if self.network is not None:
            for can_id in self.board_of:
                self.network.unsubscribe(can_id, self._on_frame)
        self.network = None

    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self._frames.append((can_id, host_now_ns(), bytes(data)))

    def take(self) -> list[BoardSample]:
        """The frames received since the last call, decoded and numbered, in arrival order."""
        with self._lock:
            frames, self._frames = self._frames, []
        out = []
        now = time.monotonic()
        for can_id, host_ns, data in frames:
            name, device = self.board_of[can_id]
            self._last_heard[device] = now
            try:
                signals = pb.decode(can_id, data)
            except CodecError:
                self.undecodable += 1  # a short or foreign frame on a board's id: counted, not recorded
                continue
            counter = self._counters.get(can_id)
            if counter is None:
                counter = self._counters[can_id] = _Counter(pb.counter_modulo(name))
            seq = counter.number(int(signals["Counter"]))
            out.append(BoardSample(name, host_ns, seq, signals))
        return out

    def check(self) -> None:
        """Raise :class:`BoardLostError` for a board silent longer than its limit."""
        now = time.monotonic()
        for name, heard in self._last_heard.items():
            if now - heard > self.limit_s[name]:
                raise BoardLostError(f"{name} (node {self.nodes[name]:#x}) sent no frame for "
                                     f"{now - heard:.2f} s (power or cable?)")  # fmt: skip

    def send_pressures(self, setpoint_pa: list[float], regulate: list[bool]) -> None:
        """One PressureCommand to the main board: each link's set-point and whether it is regulated."""
        self._command_counter = (self._command_counter + 1) % pb.COMMAND_COUNTER_MODULO
        frame = pb.encode(pb.PRESSURE_COMMAND, {
            "Setpoint1": float(setpoint_pa[0]), "Setpoint2": float(setpoint_pa[1]),
            "Regulate1": int(bool(regulate[0])), "Regulate2": int(bool(regulate[1])),
            "Counter": self._command_counter})  # fmt: skip
        self.network.send_message(frame.can_id, frame.data)
