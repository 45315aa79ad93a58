"""One XM430's control table as the servo keeps it: what a write may change and the error it gets otherwise.

The items (address, size, access, range) are those of :mod:`acquisition.codecs.xm430`. A write is checked
whole and stored only if every byte of it is accepted, in this order (the first refusal is the reply):

- Data Length Error (5): the write does not start at the first byte of an item or stops inside one;
- Data Range Error (4): it starts at an unused address (an XM430 answers a 1-byte write to address 562 so,
  DynamixelSDK issue #148), or a value lies outside the item's range;
- Access Error (7): a read-only item, or an EEPROM item (addresses < 64) while Torque Enable is 1
  (confirmed on an XL430, DynamixelSDK issue #306) — checked before the value (unconfirmed order);
- Data Limit Error (6): a value outside its limit items (Goal Position outside Min/Max Position Limit in
  position mode, Goal PWM/Current/Velocity outside ± PWM/Current/Velocity Limit).

Unused bytes inside a multi-item write are skipped. While a hardware error is latched, Torque Enable stays 0
whatever is written (only a reboot clears it; the reply carries just the Alert bit, no error number:
unconfirmed). Indirect Data bytes stand for the bytes their Indirect
Address points at (RAM 64–661), inheriting their size, access and range; one pointing into Indirect Data is
plain storage (the initial state).
"""

from __future__ import annotations

from acquisition.codecs import dynamixel as dx
from acquisition.codecs import xm430
from acquisition.codecs.xm430 import OWNER, Item

_INDIRECT = tuple(
    range(start, start + xm430.INDIRECT_BLOCK) for start in (xm430.INDIRECT_DATA_1, xm430.INDIRECT_DATA_29)
)
_PRESENT = (dx.REALTIME_TICK[0], dx.PRESENT_TEMPERATURE[0] + 1)  # what ``ServoHardware.sense`` refreshes


def _is_indirect_data(address: int) -> bool:
    return any(address in block for block in _INDIRECT)


def _overlaps_indirect(address: int, length: int) -> bool:
    return any(address < block.stop and block.start < address + length for block in _INDIRECT)


class ControlTable:
    """One servo's control table: typed access by (address, size), and the servo's checked read/write.
    ``serial`` is the ID the servo had when made: it names the servo to the hardware behind it for good,
    whatever ID the host gives it later."""

    def __init__(self, dxl_id: int) -> None:
        self.serial = dxl_id
        self.data = xm430.default_table()
        self.set(dx.ID, dxl_id)
        self.set(dx.BAUD_RATE, 3)  # the lab's buses run at 1 Mbps

    # ------------------------------------------------------------------------------- raw access
    def get(self, item: tuple[int, int], signed: bool = False) -> int:
        address, size = item
        return int.from_bytes(self.data[address : address + size], "little", signed=signed)

    def set(self, item: tuple[int, int], value: int) -> None:
        address, size = item
        self.data[address : address + size] = (int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little")

    @property
    def dxl_id(self) -> int:
        return self.data[dx.ID[0]]

    @property
    def torque_on(self) -> bool:
        return bool(self.data[dx.TORQUE_ENABLE[0]])

    @property
    def alert(self) -> int:
        """The status packets' Alert bit (0x80) while a hardware error is latched."""
        return dx.ERR_HARDWARE_ALERT if self.data[dx.HARDWARE_ERROR_STATUS[0]] else 0

    def senses(self, address: int, length: int) -> bool:
        """Whether a read of ``length`` bytes at ``address`` needs the present values refreshed first."""
        lo, hi = _PRESENT
        return (address < hi and lo < address + length) or _overlaps_indirect(address, length)

    # ---------------------------------------------------------------------------- servo access
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error, data) for a Read of ``length`` bytes: past the table's end → Access Error (P2 wording;
        unconfirmed on an XM430), answered with zeros of the asked length, as ROBOTIS's own slave does."""
        if length == 0:
            return dx.ERR_DATA_LENGTH, b""
        if address + length > xm430.TABLE_SIZE:
            return dx.ERR_ACCESS, bytes(length if length <= xm430.TABLE_SIZE else 0)
        raw = bytes(self.data[address : address + length])
        if not _overlaps_indirect(address, length):
            return 0, raw
        out = bytearray(raw)
        for k in range(length):
            target = self._target(address + k)
            if target is not None:
                out[k] = self.data[target]
        return 0, bytes(out)

    def write(self, address: int, data: bytes) -> int:
        """Check a Write of ``data`` at ``address``; store it only if the whole of it is accepted. Returns
        the status error number (0: stored)."""
        error, chunks, items = self._check_span(address, data, indirect=True)
        if error:
            return error
        candidate = bytearray(self.data)
        for start, chunk in chunks:
            candidate[start : start + len(chunk)] = chunk
        for item in items:
            error = self._check_value(item, candidate)
            if error:
                return error
        if self.alert:  # "REBOOT is the only method to reset Torque Enable to 1" after a hardware error
            candidate[dx.TORQUE_ENABLE[0]] = 0
        self.data[:] = candidate
        return 0

    # -------------------------------------------------------------------------------- internals
    def _target(self, address: int) -> int | None:
        """Where Indirect Data byte ``address`` points (None: plain storage, or not indirect data)."""
        pointer = xm430.indirect_data_address(address)
        if pointer is None:
            return None
        target = int.from_bytes(self.data[pointer : pointer + 2], "little")
        if target >= xm430.TABLE_SIZE or _is_indirect_data(target):
            return None
        return target

    def _check_span(self, address: int, data: bytes, indirect: bool) -> tuple[int, list, list[Item]]:
        """Structure and access of a write: (error, [(address, bytes) to store], [items whose value to
        check])."""
        end = address + len(data)
        if not data:
            return dx.ERR_DATA_LENGTH, [], []
        if end > xm430.TABLE_SIZE or OWNER[address] is None:
            return dx.ERR_DATA_RANGE, [], []
        first, last = OWNER[address], OWNER[end - 1]
        if first.address != address or (last is not None and last.end != end):
            return dx.ERR_DATA_LENGTH, [], []
        chunks: list[tuple[int, bytes]] = []
        items: list[Item] = []
        a = address
        while a < end:
            item = OWNER[a]
            if item is None:  # an unused byte between items: skipped
                a += 1
                continue
            if not item.writable or (item.eeprom and self.torque_on):
                return dx.ERR_ACCESS, [], []
            target = self._target(a) if indirect else None
            if target is None:
                chunks.append((a, data[a - address : item.end - address]))
                items.append(item)
                a = item.end
                continue
            n = 1  # the run of Indirect Data bytes pointing at consecutive addresses: a write there
            while a + n < end and self._target(a + n) == target + n:
                n += 1
            if target < xm430.EEPROM_END:
                return dx.ERR_ACCESS, [], []
            error, more_chunks, more_items = self._check_span(
                target, data[a - address : a - address + n], False
            )
            if error:
                return error, [], []
            chunks += more_chunks
            items += more_items
            a += n
        return 0, chunks, items

    def _check_value(self, item: Item, table: bytearray) -> int:
        value = item.decode(table[item.address : item.end])
        if item.values is not None and value not in item.values:
            return dx.ERR_DATA_RANGE
        high = (1 << (8 * item.size)) - 1 if item.high is None else item.high
        if not item.low <= value <= high:
            return dx.ERR_DATA_RANGE
        if item.limit is not None:
            mode = table[dx.OPERATING_MODE[0]]
            if item.limit_modes is None or mode in item.limit_modes:
                low_item, high_item = item.limit
                top = self._value_at(high_item, table)
                bottom = -top if low_item is None else self._value_at(low_item, table)
                if not bottom <= value <= top:
                    return dx.ERR_DATA_LIMIT
        return 0

    @staticmethod
    def _value_at(address: int, table: bytearray) -> int:
        item = xm430.BY_ADDRESS[address]
        return item.decode(table[item.address : item.end])
