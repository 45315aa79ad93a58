"""The XM430 emulator fails the way the servo does, and the driver says so.

dynamixel-sdk's own calls (PacketHandler.write4ByteTxRx, read2ByteTxRx, GroupSyncWrite, …) through its real
PortHandler on the emulator's pty get the XM430's status error numbers: 4 Data Range, 5 Data Length,
6 Data Limit, 7 Access, 2 Instruction; a corrupted instruction gets no reply; a new ID is honoured; Sync and
Bulk Writes store nothing a Write would refuse. Then ServoBus turns each number into its own error class
and a message naming the servo, the item, what the servo said and what to do.
"""

import contextlib
import logging
import os
import select
import struct
import threading
import time
import tty

import numpy as np
import pytest
from conftest import emulator_host
from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkWrite,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from acquisition.codecs import dynamixel as dx
from acquisition.devices.servo_bus import ServoBus
from acquisition.devices.servo_errors import (
    ServoAccessError,
    ServoCrcError,
    ServoDataLengthError,
    ServoDataLimitError,
    ServoDataRangeError,
    ServoHardwareAlert,
    ServoInstructionError,
    ServoResultFail,
    ServoStatusError,
    status_error,
)
from acquisition.errors import DeviceError, DeviceReplyError
from twin.emulators.dynamixel import demo_bus

DEMO = "servo_bus=twin.emulators.dynamixel:demo_bus"
RANGE, LENGTH, LIMIT, ACCESS, INSTRUCTION = (
    dx.ERR_DATA_RANGE,
    dx.ERR_DATA_LENGTH,
    dx.ERR_DATA_LIMIT,
    dx.ERR_ACCESS,
    dx.ERR_INSTRUCTION,
)


@pytest.fixture(scope="module")
def bus_port(tmp_path_factory):
    """One emulated bus (IDs 1, 2) for the module; each test leaves its servos as it found them."""
    with emulator_host(tmp_path_factory.mktemp("dxl-errors") / "run", DEMO) as ports:
        yield ports["servo_bus"]


@pytest.fixture
def sdk(bus_port):
    """The SDK's PortHandler and PacketHandler on the bus, both servos' torque off."""
    port, packet = PortHandler(bus_port), PacketHandler(2.0)
    assert port.openPort() and port.setBaudRate(1_000_000)
    try:
        for i in (1, 2):
            assert packet.write1ByteTxRx(port, i, 64, 0) == (COMM_SUCCESS, 0)
        yield port, packet
    finally:
        port.closePort()


def _no_reply(port) -> bool:
    """Nothing arrives within the SDK's status timeout."""
    port.setPacketTimeout(11)
    return PacketHandler(2.0).rxPacket(port, False)[1] == COMM_RX_TIMEOUT


# ------------------------------------------------------------------------- the SDK's own calls
def test_goal_position_outside_the_position_limits_is_a_data_limit_error(sdk):
    port, packet = sdk
    assert packet.write4ByteTxRx(port, 1, 116, 3000) == (COMM_SUCCESS, 0)
    assert packet.write4ByteTxRx(port, 1, 116, 5000) == (COMM_SUCCESS, LIMIT), "Max Position Limit is 4095"
    assert packet.write4ByteTxRx(port, 1, 116, -1 & 0xFFFFFFFF) == (COMM_SUCCESS, LIMIT)
    assert packet.read4ByteTxRx(port, 1, 116) == (3000, COMM_SUCCESS, 0), "nothing stored on error"
    assert packet.write4ByteTxRx(port, 1, 48, 3500) == (COMM_SUCCESS, 0)  # a narrower limit (torque off)
    try:
        assert packet.write4ByteTxRx(port, 1, 116, 3600) == (COMM_SUCCESS, LIMIT)
    finally:
        assert packet.write4ByteTxRx(port, 1, 48, 4095) == (COMM_SUCCESS, 0)
    # extended position mode: no limit items, the range ±1,048,575 instead
    assert packet.write1ByteTxRx(port, 1, 11, 4) == (COMM_SUCCESS, 0)
    try:
        assert packet.write4ByteTxRx(port, 1, 116, 5000) == (COMM_SUCCESS, 0)
        assert packet.write4ByteTxRx(port, 1, 116, 2_000_000) == (COMM_SUCCESS, RANGE)
    finally:
        assert packet.write1ByteTxRx(port, 1, 11, 3) == (COMM_SUCCESS, 0)
        assert packet.write4ByteTxRx(port, 1, 116, 2048) == (COMM_SUCCESS, 0)
    # the goals bounded by ± a limit item
    assert packet.write2ByteTxRx(port, 1, 102, 1000) == (COMM_SUCCESS, 0)
    assert packet.write2ByteTxRx(port, 1, 38, 500) == (COMM_SUCCESS, 0)  # Current Limit
    try:
        assert packet.write2ByteTxRx(port, 1, 102, 600) == (COMM_SUCCESS, LIMIT)
        assert packet.write2ByteTxRx(port, 1, 102, -600 & 0xFFFF) == (COMM_SUCCESS, LIMIT)
    finally:
        assert packet.write2ByteTxRx(port, 1, 38, 1193) == (COMM_SUCCESS, 0)
    assert packet.write4ByteTxRx(port, 1, 104, 351) == (COMM_SUCCESS, LIMIT), "Velocity Limit is 350"


def test_values_outside_an_items_range_are_data_range_errors(sdk):
    port, packet = sdk
    assert packet.write1ByteTxRx(port, 1, 64, 7) == (COMM_SUCCESS, RANGE), "Torque Enable is 0 or 1"
    assert packet.write1ByteTxRx(port, 1, 11, 99) == (COMM_SUCCESS, RANGE), "Operating Mode 0,1,3,4,5,16"
    assert packet.write1ByteTxRx(port, 1, 11, 2) == (COMM_SUCCESS, RANGE)
    assert packet.write4ByteTxRx(port, 1, 112, 40_000) == (COMM_SUCCESS, RANGE), "Profile Velocity ≤ 32767"
    assert packet.write1ByteTxRx(port, 1, 68, 3) == (COMM_SUCCESS, RANGE), "Status Return Level 0–2"
    assert packet.write1ByteTxRx(port, 1, 7, 253) == (COMM_SUCCESS, RANGE), "IDs end at 252"
    assert packet.read1ByteTxRx(port, 1, 64) == (0, COMM_SUCCESS, 0)
    assert packet.read1ByteTxRx(port, 1, 11) == (3, COMM_SUCCESS, 0)
    assert packet.write1ByteTxRx(port, 1, 562, 1) == (COMM_SUCCESS, RANGE), "an unused address (as an XM430)"


def test_read_only_items_and_locked_eeprom_are_access_errors(sdk):
    port, packet = sdk
    assert packet.write2ByteTxRx(port, 1, 0, 1021) == (COMM_SUCCESS, ACCESS), "Model Number, torque off"
    assert packet.write4ByteTxRx(port, 1, 132, 100) == (COMM_SUCCESS, ACCESS), "Present Position"
    assert packet.read2ByteTxRx(port, 1, 0) == (dx.XM430_W350_MODEL, COMM_SUCCESS, 0)
    assert packet.write1ByteTxRx(port, 1, 64, 1) == (COMM_SUCCESS, 0)
    try:
        assert packet.write1ByteTxRx(port, 1, 7, 9) == (COMM_SUCCESS, ACCESS), "ID is EEPROM: torque on"
        assert packet.write1ByteTxRx(port, 1, 11, 99) == (COMM_SUCCESS, ACCESS), "access before range"
        assert packet.write4ByteTxRx(port, 1, 48, 3000) == (COMM_SUCCESS, ACCESS)
        assert packet.write1ByteTxRx(port, 1, 65, 1) == (COMM_SUCCESS, 0), "RAM stays writable"
    finally:
        assert packet.write1ByteTxRx(port, 1, 64, 0) == (COMM_SUCCESS, 0)
    assert packet.write1ByteTxRx(port, 1, 11, 4) == (COMM_SUCCESS, 0), "torque off: EEPROM writable"
    assert packet.write1ByteTxRx(port, 1, 11, 3) == (COMM_SUCCESS, 0)


def test_a_write_that_cuts_an_item_is_a_data_length_error(sdk):
    port, packet = sdk
    assert packet.write2ByteTxRx(port, 1, 116, 100) == (COMM_SUCCESS, LENGTH), "Goal Position is 4 bytes"
    assert packet.write1ByteTxRx(port, 1, 117, 1) == (COMM_SUCCESS, LENGTH), "from inside the item"
    assert packet.writeTxRx(port, 1, 108, 8, list(struct.pack("<ii", 0, 0))) == (COMM_SUCCESS, 0), (
        "two whole items in one write (Profile Acceleration, Profile Velocity)"
    )


def test_the_whole_control_table_answers_to_661(sdk):
    port, packet = sdk
    assert packet.read2ByteTxRx(port, 1, 168) == (224, COMM_SUCCESS, 0), "Indirect Address 1"
    assert packet.read2ByteTxRx(port, 1, 632) == (661, COMM_SUCCESS, 0), "Indirect Address 56"
    assert packet.read1ByteTxRx(port, 1, 661) == (0, COMM_SUCCESS, 0), "Indirect Data 56"
    assert packet.write1ByteTxRx(port, 1, 661, 7) == (COMM_SUCCESS, 0)
    assert packet.read1ByteTxRx(port, 1, 661) == (7, COMM_SUCCESS, 0)
    # past the end: Access Error, and the SDK's read4ByteTxRx does not index a missing payload
    assert packet.read4ByteTxRx(port, 1, 660)[1:] == (COMM_SUCCESS, ACCESS)


def test_indirect_data_inherits_its_targets_access_and_limits(sdk):
    port, packet = sdk
    for k in range(4):  # Indirect Data 1–4 → Goal Position, 5–8 → Present Position
        assert packet.write2ByteTxRx(port, 1, 168 + 2 * k, 116 + k) == (COMM_SUCCESS, 0)
        assert packet.write2ByteTxRx(port, 1, 176 + 2 * k, 132 + k) == (COMM_SUCCESS, 0)
    try:
        assert packet.write4ByteTxRx(port, 1, 224, 2222) == (COMM_SUCCESS, 0)
        assert packet.read4ByteTxRx(port, 1, 116) == (2222, COMM_SUCCESS, 0)
        assert packet.write4ByteTxRx(port, 1, 224, 5000) == (COMM_SUCCESS, LIMIT)
        assert packet.write1ByteTxRx(port, 1, 224, 1) == (COMM_SUCCESS, LENGTH), "1 byte of Goal Position"
        assert packet.write4ByteTxRx(port, 1, 228, 100) == (COMM_SUCCESS, ACCESS), "Present Position"
        present = packet.read4ByteTxRx(port, 1, 132)[0]
        assert packet.read4ByteTxRx(port, 1, 228) == (present, COMM_SUCCESS, 0)
        assert packet.write2ByteTxRx(port, 1, 168, 11) == (COMM_SUCCESS, RANGE), "EEPROM cannot be a target"
    finally:
        for k in range(8):
            assert packet.write2ByteTxRx(port, 1, 168 + 2 * k, 224 + k) == (COMM_SUCCESS, 0)
        assert packet.write4ByteTxRx(port, 1, 116, 2048) == (COMM_SUCCESS, 0)


def test_instruction_errors(sdk):
    port, packet = sdk

    def transact(inst: int) -> list[int]:  # txRxPacket does not wait for an Action's status: by hand
        assert packet.txPacket(port, [0, 0, 0, 0, 1, 3, 0, inst, 0, 0]) == COMM_SUCCESS  # ID 1, LEN 3
        port.setPacketTimeout(11)
        rx, result = packet.rxPacket(port, False)
        assert result == COMM_SUCCESS
        return rx

    assert transact(0x77)[8] == INSTRUCTION, "an unknown instruction"
    assert transact(dx.ACTION)[8] == INSTRUCTION, "Action without Reg Write"
    assert packet.regWriteTxRx(port, 1, 116, 4, list(struct.pack("<i", 5000))) == (COMM_SUCCESS, LIMIT)
    assert packet.regWriteTxRx(port, 1, 116, 4, list(struct.pack("<i", 2100))) == (COMM_SUCCESS, 0)
    assert packet.read1ByteTxRx(port, 1, 69) == (1, COMM_SUCCESS, 0), "Registered Instruction"
    assert packet.read4ByteTxRx(port, 1, 116)[0] != 2100, "not before Action"
    assert transact(dx.ACTION)[8] == 0
    assert packet.read4ByteTxRx(port, 1, 116) == (2100, COMM_SUCCESS, 0)
    assert packet.read1ByteTxRx(port, 1, 69) == (0, COMM_SUCCESS, 0)
    assert packet.write4ByteTxRx(port, 1, 116, 2048) == (COMM_SUCCESS, 0)


def test_a_corrupted_instruction_gets_no_reply(sdk):
    """A real servo drops a packet that fails its CRC (it cannot trust the ID): silence, not a CRC Error."""
    port, packet = sdk
    bad = bytearray(dx.instruction(1, dx.WRITE, struct.pack("<HI", 116, 3000)))
    bad[-1] ^= 0x5A
    port.clearPort()
    port.writePort(bytes(bad))
    assert _no_reply(port)
    assert packet.read4ByteTxRx(port, 1, 116)[0] != 3000, "nothing executed"
    assert packet.ping(port, 1) == (dx.XM430_W350_MODEL, COMM_SUCCESS, 0), "the next packet is answered"


def test_a_new_id_is_honoured(sdk):
    port, packet = sdk
    assert packet.write1ByteTxRx(port, 2, 7, 7) == (COMM_SUCCESS, 0), "acknowledged from the old ID"
    try:
        assert packet.ping(port, 7) == (dx.XM430_W350_MODEL, COMM_SUCCESS, 0)
        assert packet.ping(port, 2)[1] == COMM_RX_TIMEOUT
        assert packet.read1ByteTxRx(port, 7, 7) == (7, COMM_SUCCESS, 0)
    finally:
        assert packet.write1ByteTxRx(port, 7, 7, 2) == (COMM_SUCCESS, 0)
    assert packet.ping(port, 2) == (dx.XM430_W350_MODEL, COMM_SUCCESS, 0)
    assert packet.ping(port, 7)[1] == COMM_RX_TIMEOUT


def test_sync_and_bulk_writes_check_each_servo_and_never_answer(sdk):
    port, packet = sdk
    for i in (1, 2):
        assert packet.write4ByteTxRx(port, i, 116, 2048) == (COMM_SUCCESS, 0)
    writer = GroupSyncWrite(port, packet, 116, 4)
    writer.addParam(1, list(struct.pack("<i", 5000)))  # outside Max Position Limit
    writer.addParam(2, list(struct.pack("<i", 2100)))
    assert writer.txPacket() == COMM_SUCCESS
    assert _no_reply(port), "no status to a Sync Write"
    reader = GroupSyncRead(port, packet, 116, 4)
    for i in (1, 2):
        reader.addParam(i)
    assert reader.txRxPacket() == COMM_SUCCESS
    assert [reader.getData(i, 116, 4) for i in (1, 2)] == [2048, 2100], "servo 1 stored nothing"

    bulk = GroupBulkWrite(port, packet)
    bulk.addParam(1, 64, 1, [7])  # Torque Enable out of range
    bulk.addParam(2, 65, 1, [1])  # LED on
    assert bulk.txPacket() == COMM_SUCCESS
    assert _no_reply(port)
    assert packet.read1ByteTxRx(port, 1, 64) == (0, COMM_SUCCESS, 0)
    assert packet.read1ByteTxRx(port, 2, 65) == (1, COMM_SUCCESS, 0)
    assert packet.write1ByteTxRx(port, BROADCAST_ID, 65, 0) == (COMM_SUCCESS, 0)  # the SDK waits for none
    assert _no_reply(port), "no status to a broadcast Write"
    assert packet.read1ByteTxRx(port, 2, 65) == (0, COMM_SUCCESS, 0)


def test_status_return_level_1_answers_reads_only(sdk):
    port, packet = sdk
    assert packet.write1ByteTxRx(port, 1, 68, 1) == (COMM_SUCCESS, 0), "answered at the level it came in"
    try:
        assert packet.read1ByteTxRx(port, 1, 68) == (1, COMM_SUCCESS, 0)
        assert packet.write1ByteTxRx(port, 1, 65, 1)[0] == COMM_RX_TIMEOUT, "no status to a write"
        assert packet.read1ByteTxRx(port, 1, 65) == (1, COMM_SUCCESS, 0), "the write was done"
    finally:
        assert packet.write1ByteTxOnly(port, 1, 68, 2) == COMM_SUCCESS  # unanswered: level 1 when it came
        assert packet.write1ByteTxRx(port, 1, 65, 0) == (COMM_SUCCESS, 0)


# ------------------------------------------------------------------------------ the driver's messages
def test_the_driver_names_servo_item_error_and_remedy(bus_port):
    with ServoBus(bus_port, ids=[1, 2]) as bus:
        bus.set_torque(False)
        with pytest.raises(ServoDataLimitError) as limit:
            bus.write_item(1, dx.GOAL_POSITION, 5000)
        message = str(limit.value)
        expected = (
            "Dynamixel bus on",
            "servo ID 1 refused writing 5000 to Goal Position (address 116)",
            "Data Limit Error (6)",
            "command a value within Min Position Limit (52) … Max Position Limit (48)",
        )
        for part in expected:
            assert part in message
        assert (limit.value.dxl_id, limit.value.address, limit.value.error) == (1, 116, 6)
        assert isinstance(limit.value, DeviceReplyError) and isinstance(limit.value, DeviceError)

        with pytest.raises(ServoDataRangeError, match=r"Torque Enable \(address 64\).*range: 0 … 1"):
            bus.write_item(2, dx.TORQUE_ENABLE, 7)
        with pytest.raises(ServoDataRangeError, match=r"one of 0, 1, 3, 4, 5, 16"):
            bus.write_item(2, dx.OPERATING_MODE, 99)
        with pytest.raises(ServoAccessError, match=r"Model Number \(address 0\).*read-only"):
            bus.write_item(1, dx.MODEL_NUMBER, 1)
        with pytest.raises(
            ServoDataLengthError, match=r"write Goal Position whole: 4 bytes from address 116"
        ):
            bus.write_item(1, (116, 2), 1)
        with pytest.raises(
            ServoAccessError, match=r"servo ID 1 refused reading address 660.*ends at address 661"
        ):
            bus.read_item(1, (660, 4))
        bus.set_torque(True)
        try:
            with pytest.raises(
                ServoAccessError, match=r"ID 2 .*Operating Mode.*Access Error \(7\).*torque off"
            ):
                bus.write_item(2, dx.OPERATING_MODE, 3)
            bus.write_goals(np.zeros(2))  # a write the servos take still goes through
        finally:
            bus.set_torque(False)
        assert bus.read_item(1, dx.MODEL_NUMBER) == dx.XM430_W350_MODEL
        assert bus.read_state().alert.tolist() == [False, False]


def test_every_error_number_has_its_class_and_advice():
    where = "Dynamixel bus on /dev/ttyUSB0"
    cases = {
        dx.ERR_RESULT_FAIL: (ServoResultFail, "Hardware Error Status"),
        dx.ERR_INSTRUCTION: (ServoInstructionError, "protocol version"),
        dx.ERR_CRC: (ServoCrcError, "cable"),
        dx.ERR_DATA_RANGE: (ServoDataRangeError, "range"),
        dx.ERR_DATA_LENGTH: (ServoDataLengthError, "whole"),
        dx.ERR_DATA_LIMIT: (ServoDataLimitError, "within"),
        dx.ERR_ACCESS: (ServoAccessError, "torque off"),
    }
    for number, (cls, advice) in cases.items():
        item = dx.ID if number == dx.ERR_ACCESS else dx.GOAL_POSITION
        exc = status_error(where, 3, number, "writing 1 to", *item)
        assert type(exc) is cls and exc.number == number
        assert str(exc).startswith(f"{where}: servo ID 3 refused writing 1 to") and advice in str(exc)
        assert dx.ERROR_NAMES[number] in str(exc)
    alert = status_error(where, 3, 0x80, "a ping", hardware=0x24)
    assert type(alert) is ServoHardwareAlert and isinstance(alert, ServoStatusError)
    assert "overheating, overload" in str(alert) and "reboot the servo" in str(alert)
    both = status_error(where, 3, 0x80 | dx.ERR_DATA_LIMIT, "writing 5000 to", *dx.GOAL_POSITION)
    assert type(both) is ServoDataLimitError and "could not be read" in str(both)


def test_alert_bit_rides_on_every_status_while_a_hardware_error_is_latched():
    bus = demo_bus()
    bus.tables[1].set(dx.HARDWARE_ERROR_STATUS, 0x20)  # overload
    request = dx.instruction(dx.BROADCAST_ID, dx.SYNC_READ, bytes([120, 0, 16, 0, 1, 2]))
    replies = dx.PacketReader().feed(bus.feed(request, 0.0))
    assert [p.error for p in replies] == [0x80, 0]
    (refused,) = dx.PacketReader().feed(bus.feed(dx.instruction(1, dx.WRITE, struct.pack("<HB", 64, 7)), 0))
    assert refused.error == 0x80 | dx.ERR_DATA_RANGE
    bus.feed(dx.instruction(1, dx.REBOOT), 0.0)
    (pong,) = dx.PacketReader().feed(bus.feed(dx.instruction(1, dx.PING), 0.0))
    assert pong.error == 0, "a reboot clears the hardware error"


@contextlib.contextmanager
def _served(bus):
    """``bus`` on a pty served by a thread of this process (so a test can reach into its tables)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    stop = threading.Event()

    def serve() -> None:
        start = time.monotonic()
        while not stop.is_set():
            if select.select([master], [], [], 0.02)[0]:
                reply = bus.feed(os.read(master, 4096), time.monotonic() - start)
                if reply:
                    os.write(master, reply)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield os.ttyname(slave)
    finally:
        stop.set()
        thread.join()
        os.close(master)
        os.close(slave)


def test_a_latched_hardware_error_is_reported_and_cleared_by_a_reboot(caplog):
    bus = demo_bus()
    bus.tables[1].set(dx.HARDWARE_ERROR_STATUS, 0x20)  # overload: the servo has switched its torque off
    with _served(bus) as path, caplog.at_level(logging.WARNING), ServoBus(path, ids=[1, 2]) as driver:
        assert "servo ID 1 answered a ping with its Alert bit set" in caplog.text, "opens, and says so"
        assert "0x20: overload" in caplog.text
        assert driver.read_state().alert.tolist() == [True, False], "readings still flow, flagged"
        with pytest.raises(
            ServoHardwareAlert, match=r"ID 1 .*Torque Enable.*0x20: overload.*reboot the servo"
        ):
            driver.set_torque(True)
        assert driver.read_item(1, dx.TORQUE_ENABLE) == 0, "only a reboot lets the torque on again"
        driver.set_torque(False)  # a safe stop is not refused: the servo is already limp
        driver.reboot(1)
        driver.set_torque(True)
        assert driver.read_item(1, dx.TORQUE_ENABLE) == 1
        assert driver.read_state().alert.tolist() == [False, False]
        driver.set_torque(False)
