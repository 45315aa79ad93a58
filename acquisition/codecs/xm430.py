"""The XM430-W350's control table: every item's address, size, access, initial value and range.

From the ROBOTIS e-manual (``docs/en/dxl/x/xm430-w350.md`` and its ``_includes/en/dxl/control_table_*``):
EEPROM 0–63 (writable only with Torque Enable = 0), RAM 64–227 and Indirect Address/Data 29–56 at 578–661.
Shared by the driver (to name an item in an error message) and the emulator (to refuse what the servo
refuses). Values outside ``low``–``high`` (or ``values``) are a Data Range Error; a value outside the item's
*limit* items (Goal Position inside Min/Max Position Limit in position mode, Goal Current inside ±Current
Limit, …) is a Data Limit Error.
"""

from __future__ import annotations

from dataclasses import dataclass

TABLE_SIZE = 662  # addresses 0 … 661
EEPROM_END = 64
POSITION_MODE = 3
OPERATING_MODES = frozenset({0, 1, 3, 4, 5, 16})  # current, velocity, position, extended, current-based, PWM
MAX_ID = 252  # 253 … 255 are reserved (0xFE broadcast)

INDIRECT_ADDRESS_1, INDIRECT_DATA_1 = 168, 224  # Indirect Address/Data 1–28
INDIRECT_ADDRESS_29, INDIRECT_DATA_29 = 578, 634  # Indirect Address/Data 29–56
INDIRECT_BLOCK = 28
INDIRECT_TARGETS = (EEPROM_END, TABLE_SIZE - 1)  # an indirect address may point at RAM only


@dataclass(frozen=True)
class Item:
    """One control-table item. ``limit`` names the items bounding it: (low item, high item) addresses, the
    low one ``None`` for ±high; it applies in every operating mode unless ``limit_modes`` says which."""

    name: str
    address: int
    size: int
    access: str = "RW"  # "R" or "RW"
    default: int = 0
    low: int = 0
    high: int | None = None  # None: the whole unsigned range of ``size`` bytes
    signed: bool = False
    values: frozenset[int] | None = None
    limit: tuple[int | None, int] | None = None
    limit_modes: frozenset[int] | None = None

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END

    @property
    def writable(self) -> bool:
        return self.access == "RW"

    @property
    def end(self) -> int:
        return self.address + self.size

    def decode(self, raw: bytes) -> int:
        return int.from_bytes(raw, "little", signed=self.signed)

    def encode(self, value: int) -> bytes:
        return (int(value) & ((1 << (8 * self.size)) - 1)).to_bytes(self.size, "little")

    def describe_range(self) -> str:
        if self.values is not None:
            return "one of " + ", ".join(str(v) for v in sorted(self.values))
        high = (1 << (8 * self.size)) - 1 if self.high is None else self.high
        return f"{self.low} … {high}"


def _items() -> tuple[Item, ...]:
    s14 = 16383  # gains
    items = [
        # EEPROM
        Item("Model Number", 0, 2, "R", 1020),
        Item("Model Information", 2, 4, "R"),
        Item("Firmware Version", 6, 1, "R", 46),
        Item("ID", 7, 1, default=1, high=MAX_ID),
        Item("Baud Rate", 8, 1, default=1, high=7),
        Item("Return Delay Time", 9, 1, default=250, high=254),
        Item("Drive Mode", 10, 1, high=13),
        Item("Operating Mode", 11, 1, default=POSITION_MODE, values=OPERATING_MODES),
        Item("Secondary(Shadow) ID", 12, 1, default=255),
        Item("Protocol Version", 13, 1, default=2, low=1, high=2),
        Item("Homing Offset", 20, 4, low=-1_044_479, high=1_044_479, signed=True),
        Item("Moving Threshold", 24, 4, default=10, high=1023),
        Item("Temperature Limit", 31, 1, default=80, high=100),
        Item("Max Voltage Limit", 32, 2, default=160, low=95, high=160),
        Item("Min Voltage Limit", 34, 2, default=95, low=95, high=160),
        Item("PWM Limit", 36, 2, default=885, high=885),
        Item("Current Limit", 38, 2, default=1193, high=1193),
        Item("Acceleration Limit", 40, 4, default=32767, high=32767),
        Item("Velocity Limit", 44, 4, default=350, high=1023),
        Item("Max Position Limit", 48, 4, default=4095, high=4095),
        Item("Min Position Limit", 52, 4, default=0, high=4095),
        Item("Shutdown", 63, 1, default=52),
        # RAM
        Item("Torque Enable", 64, 1, high=1),
        Item("LED", 65, 1, high=1),
        Item("Status Return Level", 68, 1, default=2, high=2),
        Item("Registered Instruction", 69, 1, "R"),
        Item("Hardware Error Status", 70, 1, "R"),
        Item("Velocity I Gain", 76, 2, default=1920, high=s14),
        Item("Velocity P Gain", 78, 2, default=100, high=s14),
        Item("Position D Gain", 80, 2, high=s14),
        Item("Position I Gain", 82, 2, high=s14),
        Item("Position P Gain", 84, 2, default=800, high=s14),
        Item("Feedforward 2nd Gain", 88, 2, high=s14),
        Item("Feedforward 1st Gain", 90, 2, high=s14),
        Item("Bus Watchdog", 98, 1, high=127),
        Item("Goal PWM", 100, 2, low=-885, high=885, signed=True, limit=(None, 36)),
        Item("Goal Current", 102, 2, low=-1193, high=1193, signed=True, limit=(None, 38)),
        Item("Goal Velocity", 104, 4, low=-1023, high=1023, signed=True, limit=(None, 44)),
        Item("Profile Acceleration", 108, 4, high=32767),
        Item("Profile Velocity", 112, 4, high=32767),
        Item(
            "Goal Position",
            116,
            4,
            low=-1_048_575,
            high=1_048_575,
            signed=True,
            limit=(52, 48),
            limit_modes=frozenset({POSITION_MODE}),
        ),
        Item("Realtime Tick", 120, 2, "R"),
        Item("Moving", 122, 1, "R"),
        Item("Moving Status", 123, 1, "R"),
        Item("Present PWM", 124, 2, "R", signed=True),
        Item("Present Current", 126, 2, "R", signed=True),
        Item("Present Velocity", 128, 4, "R", signed=True),
        Item("Present Position", 132, 4, "R", signed=True),
        Item("Velocity Trajectory", 136, 4, "R", signed=True),
        Item("Position Trajectory", 140, 4, "R", signed=True),
        Item("Present Input Voltage", 144, 2, "R", 120),
        Item("Present Temperature", 146, 1, "R", 30),
    ]
    lo, hi = INDIRECT_TARGETS
    for addr0, data0, first in (
        (INDIRECT_ADDRESS_1, INDIRECT_DATA_1, 1),
        (INDIRECT_ADDRESS_29, INDIRECT_DATA_29, 29),
    ):
        for k in range(INDIRECT_BLOCK):
            n = first + k
            items.append(Item(f"Indirect Address {n}", addr0 + 2 * k, 2, default=data0 + k, low=lo, high=hi))
        for k in range(INDIRECT_BLOCK):
            items.append(Item(f"Indirect Data {first + k}", data0 + k, 1))
    return tuple(sorted(items, key=lambda item: item.address))


ITEMS = _items()
BY_NAME = {item.name: item for item in ITEMS}
BY_ADDRESS = {item.address: item for item in ITEMS}
OWNER: tuple[Item | None, ...] = tuple(
    next((item for item in ITEMS if item.address <= a < item.end), None) for a in range(TABLE_SIZE)
)


def item_at(address: int) -> Item | None:
    """The item covering ``address`` (None for an unused address or one past the table)."""
    return OWNER[address] if 0 <= address < TABLE_SIZE else None


def describe(address: int, size: int | None = None) -> str:
    """'Goal Position (address 116)' or 'address 300 (unused)', for messages."""
    item = item_at(address)
    if item is None:
        return f"address {address} (not in the XM430's control table)"
    if item.address == address and (size is None or size == item.size):
        return f"{item.name} (address {address})"
    return f"address {address} (inside {item.name}, {item.address}–{item.end - 1})"


def indirect_data_address(address: int) -> int | None:
    """The Indirect Address item that redirects Indirect Data byte ``address`` (None if not indirect data)."""
    if INDIRECT_DATA_1 <= address < INDIRECT_DATA_1 + INDIRECT_BLOCK:
        return INDIRECT_ADDRESS_1 + 2 * (address - INDIRECT_DATA_1)
    if INDIRECT_DATA_29 <= address < INDIRECT_DATA_29 + INDIRECT_BLOCK:
        return INDIRECT_ADDRESS_29 + 2 * (address - INDIRECT_DATA_29)
    return None


def default_table() -> bytearray:
    """Every item at its initial value (the table after power-on, ID 1)."""
    data = bytearray(TABLE_SIZE)
    for item in ITEMS:
        data[item.address : item.end] = item.encode(item.default)
    return data
