"""The twin's half of the built-in device kinds (:mod:`acquisition.devices.builtin_kinds` names these by
``"module:attribute"``): each kind's emulator, built on the rig, and its streams, read from the world.

An emulator factory is ``(rig, name, spec) → Emulator`` (None: nothing to serve for this description); a
device on another's bus (``spec.bus``) returns the node its bus attaches. A stream function is ``(world, name,
trace, servo_rate_hz) → {stream key: Stream}``: what device ``name`` reported during ``trace``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from acquisition.codecs import dynamixel as dx
from acquisition.codecs import popup_boards
from acquisition.codecs.board_lines import MAX_SET_PA
from acquisition.devices.kinds import device_of, kind_of, resolve
from models.robot import CAN_DIR, DeviceSpec
from twin import sensors, streams
from twin.can_bus import CanBus
from twin.devices import TwinBoardTimer, TwinJoint, TwinLinkBoard, TwinPressure, TwinServos, TwinStepper
from twin.kernel import Trace

if TYPE_CHECKING:
    from twin.emulators.base import Emulator
    from twin.emulators.popup_boards import BoardNode
    from twin.rig import Rig
    from twin.world import World

Streams = dict[str, streams.Stream]


# ------------------------------------------------------------------------------------------- emulators
def servo_bus_emulator(rig: Rig, name: str, spec: DeviceSpec) -> Emulator:
    """The Dynamixel bus: an XM430 per id of ``spec.ids`` at the description's baud and return delay (or as
    they come out of the box on a factory rig), its goal where its joint is (torque-on does not jump)."""
    from twin.emulators.dynamixel import DynamixelBusEmulator

    hardware = TwinServos(
        rig, {dxl_id: rig.robot.actuated_joints.index(joint) for joint, dxl_id in spec.ids.items()}, name
    )
    bus = DynamixelBusEmulator(sorted(spec.ids.values()), hardware, factory=rig.factory, baud=spec.baud,
                               return_delay_s=spec.return_delay_s)  # fmt: skip
    for table in bus.servos:
        joint = hardware.joints[table.serial]
        table.set(
            dx.GOAL_POSITION, int(sensors.encoder_counts(rig.world.state.out_pos[0, joint], hardware.zero))
        )
    return bus


def pressure_board_emulator(rig: Rig, name: str, spec: DeviceSpec) -> Emulator:
    """The pressure board's firmware; its set-point limit is the regulators' range (VSL 3 bar)."""
    from twin.emulators.board_firmware import PressureBoardEmulator

    board = PressureBoardEmulator(
        TwinPressure(rig), max_set_pa=min(int(rig.robot.pneumatics.regulator_max_pa), MAX_SET_PA)
    )
    board.baud = spec.baud  # the firmware's fixed rate
    return board


def stepper_board_emulator(rig: Rig, name: str, spec: DeviceSpec) -> Emulator | None:
    """The stepper board's firmware (a description without a stepper section has nothing to serve)."""
    from twin.emulators.board_firmware import StepperBoardEmulator

    if rig.robot.stepper is None:
        return None
    board = StepperBoardEmulator(TwinStepper(rig, name))
    board.baud = spec.baud  # the firmware's fixed rate
    return board


def aurora_emulator(rig: Rig, name: str, spec: DeviceSpec) -> Emulator:
    """The NDI Aurora, seeing the rig's tip coil (``rig.coil``: the control socket moves it out)."""
    from twin.emulators.aurora import AuroraEmulator

    rig.coil.counter = name
    return AuroraEmulator(rig.coil)


def can_bus_emulator(rig: Rig, name: str, spec: DeviceSpec) -> Emulator:
    """The arm's CAN bus at the description's bit rate (``baud``) with a CiA 402 drive per joint of ``ids``
    and every device whose ``bus`` is this one (its kind's emulator is the node), behind a USB-CAN adapter
    speaking slcan."""
    from twin.emulators.cia402_drive import Cia402Drive
    from twin.emulators.slcan_adapter import SlcanAdapter

    rig.can_bus = CanBus(spec.baud)
    for joint, node_id in spec.ids.items():
        drive = Cia402Drive(node_id, CAN_DIR / "popup_drive.eds", TwinJoint(rig, joint))
        rig.drives[node_id] = drive
        rig.can_bus.attach(drive)
    for board, dev in rig.robot.devices.items():
        if dev.bus is not None:
            kind = kind_of(rig.robot, board)
            if kind.emulator is None:
                raise ValueError(f"{rig.robot.name}: device {board} ({dev.driver}) cannot sit on the CAN bus")
            rig.boards[board] = resolve(kind.emulator)(rig, board, dev)
            rig.can_bus.attach(rig.boards[board])
    return SlcanAdapter(rig.can_bus)


def main_board_node(rig: Rig, name: str, spec: DeviceSpec) -> BoardNode:
    """POPUP's main board on the CAN bus, sampling the twin's pressures on its own clock."""
    from twin.emulators.popup_boards import MainBoard

    robot = rig.robot
    max_set = min(robot.pneumatics.regulator_max_pa, popup_boards.setpoint_max_pa())
    status = TwinBoardTimer(rig, name, popup_boards.STATUS_PERIOD_S)
    return MainBoard(
        TwinPressure(rig), TwinBoardTimer(rig, name, 1.0 / spec.rate_hz), status, max_set, rig.world.t
    )


def link_board_node(rig: Rig, name: str, spec: DeviceSpec) -> BoardNode:
    """A POPUP link board on the CAN bus (with the tip accelerometer if the description puts it there)."""
    from twin.emulators.popup_boards import LinkBoard

    accel_timer = None
    if device_of(rig.robot, "accelerometer") == name:
        accel_timer = TwinBoardTimer(rig, name, 1.0 / rig.robot.sensors.accelerometer.sample_rate_hz)
    return LinkBoard(spec.ids["board"], TwinLinkBoard(rig, spec.link, name),
                     TwinBoardTimer(rig, name, 1.0 / spec.rate_hz), accel_timer, rig.world.t)  # fmt: skip


# --------------------------------------------------------------------------------------------- streams
def servo_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """Sync Reads of the servo bus, polled by the host at ``servo_rate_hz``."""
    if device_of(world.robot, "joints") != name:
        return {}
    return {"servo_bus": streams.servo_stream(world.robot, world.clocks[name], trace, world.dt, servo_rate_hz,
                                              world.noise(name))}  # fmt: skip


def pressure_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """The link pressures' conversions, on the board's own clock."""
    if device_of(world.robot, "pressure") != name:
        return {}
    return {"pressure_board": streams.pressure_stream(world.robot, world.clocks[name], trace, world.dt,
                                                      world.noise(name))}  # fmt: skip


def stepper_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """The stepper board's position reports."""
    if device_of(world.robot, "stepper") != name or world.robot.stepper is None:
        return {}
    return {"stepper_board": streams.stepper_stream(world.robot, world.clocks[name], trace, world.dt,
                                                    world.noise(name))}  # fmt: skip


def tracker_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """The tracker's frames."""
    if device_of(world.robot, "tracker") != name:
        return {}
    return {"tracker": streams.tracker_stream(world.robot, world.clocks[name], trace, world.dt,
                                              world.noise(name))}  # fmt: skip


def drive_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """The CiA 402 drives' answers to the host's SYNC at the bus's rate."""
    if device_of(world.robot, "joints") != name:
        return {}
    rate = world.robot.devices[name].rate_hz or servo_rate_hz
    noise = world.noise(name)
    return {"drives": streams.drive_stream(world.robot, world.clocks[name], trace, world.dt, rate, noise)}


def link_board_streams(world: World, name: str, trace: Trace, servo_rate_hz: float) -> Streams:
    """A link board's orientation and flex sensors."""
    return {f"link_board:{name}": streams.link_board_stream(world.robot, name, world.clocks[name], trace,
                                                            world.dt, world.noise(name))}  # fmt: skip


def accelerometer_streams(world: World, name: str, trace: Trace,
                          servo_rate_hz: float) -> Streams:  # fmt: skip
    """The tip accelerometer, where the description puts it on this device; its differentiator carries the
    tip's last two positions from one read to the next (``world.tip_tail``)."""
    if device_of(world.robot, "accelerometer") != name:
        return {}
    dt, tail = world.dt, world.tip_tail
    before = tail[1] if tail is not None and abs(trace.t[0] - dt - tail[0]) < dt / 2 else None
    out = streams.accelerometer_stream(world.robot, world.clocks[name], trace, dt, world.noise(name), before)
    if trace.tip_pos.shape[1] >= 2:
        world.tip_tail = (float(trace.t[-1]), trace.tip_pos[:, -2:].copy())
    return {"accelerometer": out}
