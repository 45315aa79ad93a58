"""What a Dynamixel servo's error status means, as a DeviceError a user can act on.

Protocol 2.0 status packets carry an error byte: bits 0–6 an error number (1 Result Fail, 2 Instruction,
3 CRC, 4 Data Range, 5 Data Length, 6 Data Limit, 7 Access; ROBOTIS e-manual, protocol2), bit 7 the hardware
Alert (Hardware Error Status 70 is set and the servo has switched its torque off). Each number has its own
:class:`ServoStatusError` subclass; the message names the bus, the servo, the control-table item (from
:mod:`acquisition.codecs.xm430`), what the servo said and what to do.
"""

from __future__ import annotations

from acquisition.codecs import dynamixel as dx
from acquisition.codecs import xm430
from acquisition.errors import DeviceReplyError

# what each error number says the servo did, for messages a user can act on (ROBOTIS e-manual, protocol2)
MEANINGS = {
    dx.ERR_RESULT_FAIL: "it could not carry out the instruction",
    dx.ERR_INSTRUCTION: "it does not know the instruction, or got Action without Reg Write",
    dx.ERR_CRC: "the packet it received was corrupted",
    dx.ERR_DATA_RANGE: "the value (or the address) is outside the item's range",
    dx.ERR_DATA_LENGTH: "the write does not cover the whole item",
    dx.ERR_DATA_LIMIT: "the value is outside the servo's limit items",
    dx.ERR_ACCESS: "the item cannot be written now",
    dx.ERR_HARDWARE_ALERT: "a hardware error is latched and the servo has switched its torque off",
}


class ServoStatusError(DeviceReplyError):
    """A servo answered with an error status: ``dxl_id`` refused the item at ``address`` (None: not an
    item, e.g. a ping) with status byte ``error``. Each subclass stands for one error ``number``."""

    number = 0
    meaning = "an unknown error"

    def __init_subclass__(cls, number: int, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        cls.number, cls.meaning = number, MEANINGS[number]

    def __init__(self, message: str, dxl_id: int, address: int | None, error: int) -> None:
        super().__init__(message)
        self.dxl_id = dxl_id
        self.address = address
        self.error = error


class ServoResultFail(ServoStatusError, number=dx.ERR_RESULT_FAIL): ...


class ServoInstructionError(ServoStatusError, number=dx.ERR_INSTRUCTION): ...


class ServoCrcError(ServoStatusError, number=dx.ERR_CRC): ...


class ServoDataRangeError(ServoStatusError, number=dx.ERR_DATA_RANGE): ...


class ServoDataLengthError(ServoStatusError, number=dx.ERR_DATA_LENGTH): ...


class ServoDataLimitError(ServoStatusError, number=dx.ERR_DATA_LIMIT): ...


class ServoAccessError(ServoStatusError, number=dx.ERR_ACCESS): ...


class ServoHardwareAlert(ServoStatusError, number=dx.ERR_HARDWARE_ALERT): ...


BY_NUMBER: dict[int, type[ServoStatusError]] = {cls.number: cls for cls in ServoStatusError.__subclasses__()}
HARDWARE_ERROR_BITS = {0: "input voltage", 2: "overheating", 3: "motor encoder", 4: "electrical shock",
                       5: "overload"}  # fmt: skip


def _limits(item: xm430.Item) -> str:
    low, high = item.limit
    top = f"{xm430.BY_ADDRESS[high].name} ({high})"
    return f"± {top}" if low is None else f"{xm430.BY_ADDRESS[low].name} ({low}) … {top}"


def advice(cls: type[ServoStatusError], address: int | None, size: int | None = None) -> str:
    """What to do about ``cls`` on the item at ``address`` (``size`` bytes)."""
    item = xm430.item_at(address) if address is not None else None
    whole = item is not None and item.address == address
    if address is not None and address + (size or 1) > xm430.TABLE_SIZE:
        return (
            f"the XM430's control table ends at address {xm430.TABLE_SIZE - 1}: check the address and length"
        )
    if cls is ServoAccessError and item is not None and not item.writable:
        return f"{item.name} is read-only: nothing can write it"
    if cls is ServoAccessError and item is not None and item.eeprom:
        return "EEPROM items (addresses 0–63) are writable only with torque off: switch the torque off first"
    if cls is ServoDataRangeError and whole:
        return f"send a value in {item.name}'s range: {item.describe_range()}"
    if cls is ServoDataRangeError:
        return "check the address against the XM430's control table"
    if cls is ServoDataLimitError and whole and item.limit is not None:
        return f"command a value within {_limits(item)}, or change those limits (EEPROM: torque off first)"
    if cls is ServoDataLengthError and item is not None:
        return f"write {item.name} whole: {item.size} bytes from address {item.address}"
    if cls is ServoCrcError:
        return "check the cable, its termination and the baud rate, then retry"
    if cls is ServoInstructionError:
        return "check the protocol version (2.0) and the instruction sent"
    if cls is ServoResultFail:
        return "read Hardware Error Status (70) and reboot the servo if it is set"
    return "check the request against the XM430's control table"


def hardware_text(hardware: int | None) -> str:
    """'Hardware Error Status (70) = 0x20: overload' (or that it could not be read)."""
    if hardware is None:
        return "Hardware Error Status (70) could not be read"
    bits = ", ".join(name for bit, name in HARDWARE_ERROR_BITS.items() if hardware >> bit & 1)
    return f"Hardware Error Status (70) = 0x{hardware:02X}: {bits or 'no known bit'}"


def status_error(where: str, dxl_id: int, error: int, doing: str, address: int | None = None,
                 size: int | None = None, hardware: int | None = None) -> ServoStatusError:  # fmt: skip
    """The error for status byte ``error`` that servo ``dxl_id`` on ``where`` (the bus) answered to
    ``doing`` (e.g. 'writing 5000 to') the item at ``address``; ``hardware`` is Hardware Error Status (70),
    read after an Alert (None: not read)."""
    target = f" {xm430.describe(address, size)}" if address is not None else ""
    number = error & ~dx.ERR_HARDWARE_ALERT
    parts = []
    if number:
        cls = BY_NUMBER.get(number, ServoStatusError)
        name = dx.ERROR_NAMES.get(number, f"error {number}")
        parts.append(f"{where}: servo ID {dxl_id} refused {doing}{target}: {name} ({number}): {cls.meaning}")
        parts.append(advice(cls, address, size))
    else:
        cls = ServoHardwareAlert
        parts.append(f"{where}: servo ID {dxl_id} answered {doing}{target} with its Alert bit set")
    if error & dx.ERR_HARDWARE_ALERT:
        parts.append(
            f"Alert: {ServoHardwareAlert.meaning} ({hardware_text(hardware)}); remove the cause, then "
            "reboot the servo (Reboot instruction or power cycle)"
        )
    return cls("; ".join(parts), dxl_id, address, error)
