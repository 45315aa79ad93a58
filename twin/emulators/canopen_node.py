"""A CANopen (CiA 301) slave on the twin's bus: NMT, the SDO server, PDOs, SYNC, heartbeat and EMCY.

Its object dictionary is the device's EDS, read with canopen's parser (the same file the driver loads); the
protocol is written here, from CiA 301 (``../shared/reference/can.md`` §2), not borrowed from canopen's
``LocalNode``, so a misreading on either side shows up as a failing test instead of cancelling out.

- NMT: boot-up message, then PRE-OPERATIONAL; start / stop / pre-operational / reset node / reset
  communication (a reset restores the EDS defaults of the objects it covers and sends a boot-up again).
- SDO: expedited upload and download, segmented upload for longer values; aborts with the standard codes
  (no object, no sub-index, read-only, write-only, wrong length, value out of range, wrong state).
- PDOs, in OPERATIONAL only: RPDOs decoded by their mapping (type 254/255 applied at once, 0–240 at the next
  SYNC); TPDOs sent every n-th SYNC (type 1–240) or by event timer (254/255); mapping writes only while the
  PDO is disabled and its count is 0, as CiA 301 asks and canopen's ``save`` does.
- Heartbeat: the NMT state every ``0x1017`` ms; EMCY: code, error register and five manufacturer bytes.

Subclasses (the CiA 402 drive) hook ``on_write`` (an object was written), ``refresh`` (bring the actual
values up to date before they are read or sent) and ``on_sync``.
"""

from __future__ import annotations

import struct
from pathlib import Path

import canopen

from acquisition.codecs.can import CanFrame
from twin.can_bus import CanNode

# NMT states as the heartbeat carries them
BOOT_UP, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
NMT_START, NMT_STOP, NMT_PRE_OP, NMT_RESET_NODE, NMT_RESET_COMM = 0x01, 0x02, 0x80, 0x81, 0x82
# SDO abort codes (CiA 301 §7.2.4.3.17)
ABORT_BAD_COMMAND = 0x05040001
ABORT_WRITE_ONLY, ABORT_READ_ONLY = 0x06010001, 0x06010002
ABORT_NO_OBJECT, ABORT_NOT_MAPPABLE = 0x06020000, 0x06040041
ABORT_LENGTH = 0x06070010
ABORT_NO_SUB = 0x06090011
ABORT_VALUE_HIGH, ABORT_VALUE_LOW = 0x06090031, 0x06090032
ABORT_STATE = 0x08000022  # data cannot be transferred or stored because of the present device state
RESPONSE_S = 50e-6  # a slave's processing time between a request's end and its answer being ready
_SDO_FRAME = struct.Struct("<BHB4s")


def _pdo_entry(value: int) -> tuple[int, int, int]:
    """(index, subindex, bits) of a PDO mapping entry."""
    return value >> 16, (value >> 8) & 0xFF, value & 0xFF


class CanopenNode(CanNode):
    """A CANopen slave ``node_id`` with the object dictionary of ``eds``, powered up at rig time ``t0``."""

    def __init__(self, node_id: int, eds: Path | str, t0: float = 0.0, name: str = "") -> None:
        self.node_id = node_id
        self.name = name or f"node {node_id}"
        self.od = canopen.import_od(str(eds), node_id)
        self.values: dict[tuple[int, int], int | bytes] = {}
        self.state = BOOT_UP
        self.silent = False
        self._pending_rpdo: list[tuple[int, bytes]] = []
        self._sync_count: dict[int, int] = {}
        self._segment: tuple[bytes, int] | None = None  # an upload in progress: data and next toggle
        self._next_heartbeat: float | None = None
        self._next_event: dict[int, float] = {}
        self._boot: float | None = t0  # the boot-up message is due
        self._reset(comm_only=False)

    # -------------------------------------------------------------------------------- the dictionary
    def _variables(self):
        for index in self.od:
            obj = self.od[index]
            if isinstance(obj, canopen.objectdictionary.ODVariable):
                yield obj
            else:
                yield from (obj[sub] for sub in obj)

    def _reset(self, comm_only: bool) -> None:
        for var in self._variables():
            if not comm_only or 0x1000 <= var.index < 0x2000:
                default = var.default if var.default is not None else 0
                self.values[(var.index, var.subindex)] = default
        self._pending_rpdo.clear()
        self._sync_count.clear()
        self._next_event.clear()
        self._segment = None

    def variable(self, index: int, sub: int = 0):
        """The dictionary entry (index, sub), or None."""
        if index not in self.od:
            return None
        obj = self.od[index]
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            return obj if sub == 0 else None
        return obj[sub] if sub in obj else None

    def get(self, index: int, sub: int = 0) -> int:
        return self.values[(index, sub)]

    def set(self, index: int, value: int, sub: int = 0) -> None:
        """Set a value from the device's side (actual values, the statusword)."""
        self.values[(index, sub)] = value

    # ------------------------------------------------------------------------------------- hooks
    def on_write(self, index: int, sub: int, t: float) -> None:
        """An object was written (by SDO or RPDO)."""

    def refresh(self, t: float) -> None:
        """Bring actual values up to date (before an SDO read or a TPDO)."""

    def on_sync(self, t: float) -> None:
        """A SYNC arrived (after the buffered RPDOs were applied)."""

    # ------------------------------------------------------------------------------------ frames
    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        if self.state == BOOT_UP:
            return []
        ready = t + RESPONSE_S
        cid = frame.can_id
        if cid == 0x000 and len(frame.data) == 2:
            return self._nmt(frame.data[0], frame.data[1], ready)
        if cid == self.get(0x1005) & 0x7FF and self.state == OPERATIONAL:
            return [(ready, f) for f in self._sync(t)]
        if (
            cid == 0x600 + self.node_id
            and self.state in (PRE_OPERATIONAL, OPERATIONAL)
            and len(frame.data) == 8
        ):
            answer = self._sdo(frame.data, t)
            return [] if answer is None else [(ready, CanFrame(0x580 + self.node_id, answer))]
        if self.state == OPERATIONAL:
            self._rpdo(cid, frame.data, t)
        return []

    def next_due_s(self) -> float | None:
        due = self._boot  # the bus asks every node at every event: no list built
        if self._next_heartbeat is not None and (due is None or self._next_heartbeat < due):
            due = self._next_heartbeat
        if self._next_event:
            event = min(self._next_event.values())
            due = event if due is None or event < due else due
        return due

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        out = []
        if self._boot is not None and self._boot <= t:
            out.append((self._boot, CanFrame(0x700 + self.node_id, bytes([BOOT_UP]))))
            self.state, self._boot = PRE_OPERATIONAL, None
            self._schedule_heartbeat(out[-1][0])
        while self._next_heartbeat is not None and self._next_heartbeat <= t:
            out.append((self._next_heartbeat, CanFrame(0x700 + self.node_id, bytes([self.state]))))
            self._schedule_heartbeat(self._next_heartbeat)
        for n in list(self._next_event):
            period = self.get(0x1800 + n, 5) * 1e-3
            while n in self._next_event and self._next_event[n] <= t:
                due = self._next_event[n]
                if self.state == OPERATIONAL:
                    out.append((due, self._tpdo_frame(n, due)))
                if period > 0:
                    self._next_event[n] = due + period
                else:
                    del self._next_event[n]
        return out

    def _schedule_heartbeat(self, last: float) -> None:
        period = self.get(0x1017) * 1e-3
        self._next_heartbeat = last + period if period > 0 else None

    def emcy(self, code: int, manufacturer: bytes = b"\0" * 5) -> CanFrame:
        """The EMCY message for error ``code`` (0: error reset) with the current error register."""
        data = struct.pack("<HB", code, self.get(0x1001)) + manufacturer[:5].ljust(5, b"\0")
        return CanFrame(0x080 + self.node_id, data)

    # --------------------------------------------------------------------------------------- NMT
    def _nmt(self, command: int, target: int, ready: float) -> list[tuple[float, CanFrame]]:
        if target not in (0, self.node_id):
            return []
        if command == NMT_START:
            self.state = OPERATIONAL
            self._arm_event_timers(ready)
        elif command == NMT_STOP:
            self.state = STOPPED
        elif command == NMT_PRE_OP:
            self.state = PRE_OPERATIONAL
        elif command in (NMT_RESET_NODE, NMT_RESET_COMM):
            self.reboot(ready, comm_only=command == NMT_RESET_COMM)
        return []

    def reboot(self, t: float, comm_only: bool = False) -> None:
        """Reset (the communication objects only, or the whole node) and send the boot-up message at ``t``."""
        self._reset(comm_only)
        self.on_reset(comm_only)
        self.state, self._next_heartbeat, self._boot = BOOT_UP, None, t

    def on_reset(self, comm_only: bool) -> None:
        """After an NMT reset (the application's state, for reset node)."""

    def _arm_event_timers(self, t: float) -> None:
        self._next_event.clear()
        for n in range(4):
            if (0x1800 + n) in self.od and self._tpdo_valid(n) and self.get(0x1800 + n, 2) >= 254:
                period = self.get(0x1800 + n, 5) * 1e-3
                if period > 0:
                    self._next_event[n] = t + period

    # --------------------------------------------------------------------------------------- SDO
    def _sdo(self, data: bytes, t: float) -> bytes | None:
        cmd, index, sub, payload = _SDO_FRAME.unpack(data)
        ccs = cmd >> 5
        if ccs == 3 and self._segment is not None:  # upload segment request
            return self._upload_segment(cmd)
        if ccs == 4:  # the client aborted: no answer
            self._segment = None
            return None
        var = self.variable(index, sub)
        if var is None:
            code = ABORT_NO_SUB if index in self.od else ABORT_NO_OBJECT
            return self._abort(index, sub, code)
        if ccs == 2:  # initiate upload
            if not var.readable:
                return self._abort(index, sub, ABORT_WRITE_ONLY)
            self.refresh(t)
            raw = var.encode_raw(self.get(index, sub))
            if len(raw) <= 4:
                n = 4 - len(raw)
                return _SDO_FRAME.pack(0x43 | (n << 2), index, sub, raw.ljust(4, b"\0"))
            self._segment = (raw, 0)
            return _SDO_FRAME.pack(0x41, index, sub, struct.pack("<I", len(raw)))
        if ccs == 1:  # initiate download, expedited only
            if not cmd & 0x02:
                return self._abort(index, sub, ABORT_BAD_COMMAND)
            size = 4 - ((cmd >> 2) & 3) if cmd & 0x01 else None  # None: size not indicated
            return self._download(var, index, sub, payload, size, t)
        return self._abort(index, sub, ABORT_BAD_COMMAND)

    def _download(self, var, index: int, sub: int, payload: bytes, size: int | None, t: float) -> bytes:
        if not var.writable:
            return self._abort(index, sub, ABORT_READ_ONLY)
        expected = len(var) // 8
        if size is not None and size != expected:
            return self._abort(index, sub, ABORT_LENGTH)
        value = var.decode_raw(payload[:expected])
        if var.max is not None and value > var.max:
            return self._abort(index, sub, ABORT_VALUE_HIGH)
        if var.min is not None and value < var.min:
            return self._abort(index, sub, ABORT_VALUE_LOW)
        refused = self._check_pdo_write(index, sub, value)
        if refused:
            return self._abort(index, sub, refused)
        self.values[(index, sub)] = value
        self._after_comm_write(index, sub, t)
        self.on_write(index, sub, t)
        return _SDO_FRAME.pack(0x60, index, sub, b"\0" * 4)

    def _upload_segment(self, cmd: int) -> bytes:
        raw, toggle = self._segment
        chunk, rest = raw[:7], raw[7:]
        last = not rest
        header = (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        self._segment = None if last else (rest, toggle ^ 1)
        return bytes([header]) + chunk.ljust(7, b"\0")

    def _abort(self, index: int, sub: int, code: int) -> bytes:
        self._segment = None
        return _SDO_FRAME.pack(0x80, index, sub, struct.pack("<I", code))

    # --------------------------------------------------------------------------------------- PDO
    def _tpdo_valid(self, n: int) -> bool:
        return not self.get(0x1800 + n, 1) & 0x8000_0000

    def _check_pdo_write(self, index: int, sub: int, value: int) -> int | None:
        """CiA 301: a mapping is written only while its PDO is disabled and its count is 0; the count only
        over mappable objects that fit in 8 bytes."""
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            comm = index - 0x200
            if not self.get(comm, 1) & 0x8000_0000:
                return ABORT_STATE
            if sub == 0:
                bits = 0
                for k in range(1, value + 1):
                    entry, entry_sub, size = _pdo_entry(self.get(index, k))
                    var = self.variable(entry, entry_sub)
                    if var is None or not var.pdo_mappable:
                        return ABORT_NOT_MAPPABLE
                    bits += size
                if bits > 64:
                    return ABORT_LENGTH
            elif self.get(index, 0) != 0:
                return ABORT_STATE
        return None

    def _after_comm_write(self, index: int, sub: int, t: float) -> None:
        if index == 0x1017:
            self._schedule_heartbeat(t)
        if 0x1800 <= index <= 0x1803 and self.state == OPERATIONAL:
            self._arm_event_timers(t)

    def _mapping(self, mapping_index: int) -> list[tuple[int, int, int]]:
        return [_pdo_entry(self.get(mapping_index, k)) for k in range(1, self.get(mapping_index, 0) + 1)]

    def _rpdo(self, can_id: int, data: bytes, t: float) -> None:
        for n in range(4):
            comm = 0x1400 + n
            if comm not in self.od:
                continue
            cob = self.get(comm, 1)
            if cob & 0x8000_0000 or cob & 0x7FF != can_id:
                continue
            if self.get(comm, 2) <= 240:
                self._pending_rpdo.append((n, data))
            else:
                self._apply_rpdo(n, data, t)

    def _apply_rpdo(self, n: int, data: bytes, t: float) -> None:
        bits = int.from_bytes(data, "little")
        offset = 0
        written = []
        for index, sub, size in self._mapping(0x1600 + n):
            if offset + size > len(data) * 8:
                return  # a short RPDO is not applied (CiA 301 would send EMCY 0x8210)
            raw = ((bits >> offset) & ((1 << size) - 1)).to_bytes(max(size // 8, 1), "little")
            offset += size
            var = self.variable(index, sub)
            if var is not None:
                self.values[(index, sub)] = var.decode_raw(raw)
                written.append((index, sub))
        for index, sub in written:
            self.on_write(index, sub, t)

    def _sync(self, t: float) -> list[CanFrame]:
        pending, self._pending_rpdo = self._pending_rpdo, []
        for n, data in pending:
            self._apply_rpdo(n, data, t)
        self.on_sync(t)
        out = []
        for n in range(4):
            comm = 0x1800 + n
            if comm not in self.od or not self._tpdo_valid(n):
                continue
            kind = self.get(comm, 2)
            if 1 <= kind <= 240:
                count = self._sync_count.get(n, 0) + 1
                if count >= kind:
                    out.append(self._tpdo_frame(n, t))
                    count = 0
                self._sync_count[n] = count
        return out

    def _tpdo_frame(self, n: int, t: float) -> CanFrame:
        self.refresh(t)
        bits, offset = 0, 0
        for index, sub, size in self._mapping(0x1A00 + n):
            var = self.variable(index, sub)
            raw = var.encode_raw(self.get(index, sub)) if var is not None else b"\0" * (size // 8)
            bits |= int.from_bytes(raw, "little") << offset
            offset += size
        return CanFrame(self.get(0x1800 + n, 1) & 0x7FF, bits.to_bytes((offset + 7) // 8, "little"))
