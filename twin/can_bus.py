"""The twin's CAN bus: frames from every node serialised one at a time at the bit rate, by arbitration.

A node puts frames up for transmission (ready from a time on); when the bus falls idle, the lowest
identifier among the frames ready then wins arbitration (as dominant bits do on a real bus) and occupies the
bus for its exact length (``codecs.can.frame_bits``, stuff bits included); at its end every other node
receives it and may answer (an SDO reply, the PDOs a SYNC triggers). The bus counts what it carried, so its
load is measured, not estimated.

Frames offered while the bus is busy wait in their node's transmit queue, which is finite (``tx_queue``
frames: a CAN controller's mailboxes, sent lowest identifier first, or an adapter's firmware buffer, sent
in order: ``tx_fifo``). A bus offered more than it can carry (over 100 % load) therefore delays frames, the
highest identifiers longest, and once a node's queue is full the frames it offers next are lost: counted by
the bus (``lost``, ``dropped`` per node) and told to the node (``tx_dropped``), as a controller's
transmit-overflow flag does. Frames that waited behind others and
lost arbitration are counted too (``delayed``, ``arbitration_lost``), as is the longest wait. ``bus_off``
stands for a bus that carries nothing (a short, a missing terminator, a controller in bus-off): frames
offered then are lost, and the nodes see nothing.

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
    # frames waiting to be sent at most (ASSUMED: a CAN controller's three transmit mailboxes, as in the
    # STM32 bxCAN, and a short firmware queue in front of them, as CANopen stacks keep one transmit buffer
    # per message a node sends: SDO reply, TPDOs, heartbeat, EMCY)
    tx_queue = 8
    # its frames contend lowest identifier first (False: the mailboxes' priority mode) or in the order they
    # were queued (True: a firmware FIFO, as a USB-CAN adapter's; its own frames wait behind each other)
    tx_fifo = False

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        return []

    def next_due_s(self) -> float | None:
        """When this node next has a frame of its own to send (None: nothing scheduled)."""
        return None

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        """Its own frames due at or before ``t``."""
        return []

    def tx_dropped(self, frame: CanFrame, t: float) -> None:
        """``frame`` was lost at ``t``: this node's transmit queue was full."""

    def lost_arbitration(self, frame: CanFrame, t: float) -> None:
        """``frame`` was ready when the bus fell idle at ``t`` but a lower identifier won it."""


@dataclass
class BusCounters:
    """What the bus carried since it started: frames, bits, busy time; frames lost (a full transmit queue
    or a bus-off), frames that waited for the bus, frames that lost an arbitration (once each, however
    many they lost), and the longest wait."""

    frames: int = 0
    bits: int = 0
    busy_s: float = 0.0
    lost: int = 0
    delayed: int = 0
    arbitration_lost: int = 0
    max_wait_s: float = 0.0


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
        self.queued: dict[int, int] = {}  # id(node) → its frames waiting
        self._lost_once: set[int] = set()  # the waiting frames that lost an arbitration already
        self.dropped: dict[str, int] = {}  # node name → frames lost on its full transmit queue

    def attach(self, node: CanNode) -> None:
        self.nodes.append(node)

    def offer(self, node: CanNode, ready_s: float, frame: CanFrame) -> bool:
        """``node`` wants to send ``frame`` from ``ready_s`` on: False if it is lost (a silent node, a bus-off
        bus, or the node's transmit queue full)."""
        if node.silent:
            return False
        if self.bus_off:
            self.counters.lost += 1
            return False
        if self.queued.get(id(node), 0) >= node.tx_queue:
            self.counters.lost += 1
            self.dropped[node.name] = self.dropped.get(node.name, 0) + 1
            node.tx_dropped(frame, ready_s)
            return False
        self.queued[id(node)] = self.queued.get(id(node), 0) + 1
        heapq.heappush(self._pending, (ready_s, frame.can_id, next(self._order), frame, node))
        return True

    def next_event_s(self) -> float | None:
        """Rig time of the next thing that happens on the bus (a frame's end, a node's own frame)."""
        times = [n.next_due_s() for n in self.nodes if not n.silent]
        if self._pending:
            start, winner = self._arbitrate()
            times.append(start + self._duration(winner[3]))
        due = [t for t in times if t is not None]
        return min(due) if due else None

    def run_until(self, t: float) -> None:
        """Play the bus up to rig time ``t``: every frame that ends by then is delivered. Nodes' own frames
        are offered at their due times, in order with the frames' ends, so a late call does not fill a
        transmit queue the bus would have drained meanwhile."""
        while True:
            start = max(self.free_at, self._pending[0][0]) if self._pending else None
            if self._collect(t if start is None else min(t, start), first_only=start is None):
                continue
            if start is None:
                return
            start, winner = self._arbitrate()
            end = start + self._duration(winner[3])
            self._collect(min(end, t))  # due while the frame is on the bus: they wait in their queues
            if end > t:
                return
            self._pending.remove(winner)
            heapq.heapify(self._pending)
            self.queued[id(winner[4])] -= 1
            self._count_waits(start, winner)
            self.free_at = end
            self._deliver(winner[3], winner[4], start, end)

    def _arbitrate(self) -> tuple[float, tuple]:
        """When the next frame starts and which one it is: of the frames ready when the bus is next free (of a
        FIFO node, its oldest only), the lowest identifier (then the first offered)."""
        start = max(self.free_at, self._pending[0][0])
        heads: dict[int, int] = {}  # a FIFO node's oldest frame: only it may contend
        for p in self._pending:
            if p[4].tx_fifo:
                heads[id(p[4])] = min(heads.get(id(p[4]), p[2]), p[2])
        ready = (p for p in self._pending if p[0] <= start and (not p[4].tx_fifo or heads[id(p[4])] == p[2]))
        return start, min(ready, key=lambda p: (p[1], p[2]))

    def _count_waits(self, start: float, winner: tuple) -> None:
        """The winner's wait for the bus, and every frame ready at ``start`` that lost to it."""
        c = self.counters
        wait = start - winner[0]
        if wait > 0:
            c.delayed += 1
            c.max_wait_s = max(c.max_wait_s, wait)
        self._lost_once.discard(winner[2])
        for ready, _id, order, frame, node in self._pending:
            if ready <= start and order not in self._lost_once:  # each frame counted once, however long
                self._lost_once.add(order)
                c.arbitration_lost += 1
                node.lost_arbitration(frame, start)

    def _duration(self, frame: CanFrame) -> float:
        return frame_bits(frame) / self.bitrate

    def _collect(self, t: float, first_only: bool = False) -> bool:
        """Offer every node's frames due at or before ``t`` (``first_only``: only those of the earliest due
        time, the bus being idle: a frame then starts at once); False if none is due. The callers choose
        ``t`` so that no frame ends before it: a node's queue cannot drain meanwhile."""
        due = [(d, n) for n in self.nodes if not n.silent and (d := n.next_due_s()) is not None and d <= t]
        if not due:
            return False
        until = min(d for d, _ in due) if first_only else t
        for d, node in due:
            if d <= until:
                for ready, frame in node.produce(until):
                    self.offer(node, ready, frame)
        return True

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
            self.queued.clear()
            self._lost_once.clear()
