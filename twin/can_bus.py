"""The twin's CAN bus: frames from every node serialised one at a time at the bit rate, by arbitration.

A node puts frames up for transmission (ready from a time on); when the bus falls idle, the lowest
identifier among the frames ready then wins arbitration (as dominant bits do on a real bus) and occupies the
bus for its exact length (``codecs.can.frame_bits``, stuff bits included); at its end every other node
receives it and may answer (an SDO reply, the PDOs a SYNC triggers). The bus counts what it carried, so its
load is measured, not estimated. ``bus_off`` stands for a bus that carries nothing (a short, a missing
terminator, a controller in bus-off): frames offered then are lost, and the nodes see nothing.

Event-driven: ``run_until(t)`` plays the bus forward to rig time ``t``; ``next_event_s`` says when anything
next happens, so the pty host sleeps until then.
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass

from acquisition.codecs.can import CanFrame, frame_bits


class CanNode:
    """A node on the bus. ``receive`` is called at the end of each frame another node sent and returns the
    frames it answers with as (ready time, frame); ``next_due_s`` / ``produce`` give its own timed frames
    (heartbeats, streams)."""

    name = "node"
    silent = False  # a node without power or cut off: it neither sends nor receives

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        return []

    def next_due_s(self) -> float | None:
        """When this node next has a frame of its own to send (None: nothing scheduled)."""
        return None

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        """Its own frames due at or before ``t``."""
        return []


@dataclass
class BusCounters:
    """What the bus carried since it started: frames, bits, busy time, frames lost while bus-off."""

    frames: int = 0
    bits: int = 0
    busy_s: float = 0.0
    lost: int = 0


class CanBus:
    """The medium between ``nodes`` at ``bitrate`` bit/s; the host's adapter is a node too."""

    def __init__(self, bitrate: int, nodes: list[CanNode] | None = None) -> None:
        self.bitrate = bitrate
        self.nodes: list[CanNode] = list(nodes or [])
        self.free_at = 0.0  # when the frame on the bus ends (idle after)
        self.bus_off = False
        self.counters = BusCounters()
        self._pending: list[tuple[float, int, int, CanFrame, CanNode]] = []  # ready, id, order, frame, sender
        self._order = itertools.count()

    def attach(self, node: CanNode) -> None:
        self.nodes.append(node)

    def offer(self, node: CanNode, ready_s: float, frame: CanFrame) -> None:
        """``node`` wants to send ``frame`` from ``ready_s`` on."""
        if node.silent:
            return
        if self.bus_off:
            self.counters.lost += 1
            return
        heapq.heappush(self._pending, (ready_s, frame.can_id, next(self._order), frame, node))

    def next_event_s(self) -> float | None:
        """Rig time of the next thing that happens on the bus (a frame's end, a node's own frame)."""
        times = [n.next_due_s() for n in self.nodes if not n.silent]
        if self._pending:
            start, winner = self._arbitrate()
            times.append(start + self._duration(winner[3]))
        due = [t for t in times if t is not None]
        return min(due) if due else None

    def run_until(self, t: float) -> None:
        """Play the bus up to rig time ``t``: every frame that ends by then is delivered."""
        while True:
            self._collect(t)
            if not self._pending:
                return
            start, winner = self._arbitrate()
            end = start + self._duration(winner[3])
            if end > t:
                return
            self._pending.remove(winner)
            heapq.heapify(self._pending)
            self.free_at = end
            self._deliver(winner[3], winner[4], start, end)

    def _arbitrate(self) -> tuple[float, tuple]:
        """When the next frame starts and which one it is: of the frames ready when the bus is next free, the
        lowest identifier (then the first offered)."""
        start = max(self.free_at, self._pending[0][0])
        return start, min((p for p in self._pending if p[0] <= start), key=lambda p: (p[1], p[2]))

    def _duration(self, frame: CanFrame) -> float:
        return frame_bits(frame) / self.bitrate

    def _collect(self, t: float) -> None:
        for node in self.nodes:
            if node.silent:
                continue
            due = node.next_due_s()
            if due is not None and due <= t:
                for ready, frame in node.produce(t):
                    self.offer(node, ready, frame)

    def _deliver(self, frame: CanFrame, sender: CanNode, start: float, end: float) -> None:
        bits = frame_bits(frame)
        c = self.counters
        c.frames += 1
        c.bits += bits
        c.busy_s += end - start
        for node in self.nodes:
            if node is sender or node.silent:
                continue
            for ready, answer in node.receive(frame, end):
                self.offer(node, max(ready, end), answer)

    def set_bus_off(self, off: bool) -> None:
        """Take the bus down (nothing carried, frames offered are lost) or bring it back."""
        self.bus_off = off
        if off:
            self.counters.lost += len(self._pending)
            self._pending.clear()
