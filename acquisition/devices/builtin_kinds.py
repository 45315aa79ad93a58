"""The device kinds vslab ships: the VSL rig's (Dynamixel bus, pressure and stepper boards, NDI Aurora) and
POPUP's (the CAN bus of CiA 402 drives, its main board and link boards). Registered by name in
:data:`acquisition.devices.kinds.KINDS`; their sources, emulators and twin streams are named, not imported."""

from __future__ import annotations

from acquisition.codecs import dynamixel as dx
from acquisition.devices.kinds import DeviceKind
from acquisition.schemas import topics as T
from models.robot import DeviceSpec, RobotDescription

_SOURCES = "acquisition.recorder.sources"
_TWIN = "twin.device_kinds"
_ROWS = "twin.topics"


def _servo_joints(robot: RobotDescription, name: str) -> list[str]:
    """The position-controlled joints device ``name`` drives (the stepper's is the Nano's)."""
    drives = {j.name: j.drive for j in robot.joints}
    return [j for j in robot.devices[name].ids if drives.get(j) != "stepper"]


def _dynamixel_topics(robot: RobotDescription, name: str) -> dict:
    n = len(_servo_joints(robot, name))
    return {T.SERVO_STATE: T.servo_state(n), T.SERVO_GOAL: T.servo_goal(n)} if n else {}


def _pressure_topics(robot: RobotDescription, name: str) -> dict:
    c = robot.pneumatics.channels
    return {T.PRESSURE: T.pressure(c), T.PRESSURE_COMMAND: T.pressure_command(c)}


def _stepper_topics(robot: RobotDescription, name: str) -> dict:
    steppers = [j.name for j in robot.joints if j.drive == "stepper"]
    return {T.STEPPER: T.stepper(len(steppers))} if steppers else {}


def _tracker_topics(robot: RobotDescription, name: str) -> dict:
    return {T.TRACKER: T.TRACKER_POSE}


def _can_topics(robot: RobotDescription, name: str) -> dict:
    n = len(_servo_joints(robot, name))
    return {T.JOINT_STATE: T.joint_state(n), T.SERVO_GOAL: T.servo_goal(n)} if n else {}


def _link_board_topics(robot: RobotDescription, name: str) -> dict:
    link = robot.devices[name].link
    out = {T.link_orientation_topic(link): T.LINK_ORIENTATION, T.link_flex_topic(link): T.LINK_FLEX}
    accel = robot.sensors.accelerometer
    if accel is not None and accel.device == name:
        out[T.ACCEL] = T.ACCELERATION
    return out


def _check_link_board(robot: RobotDescription, name: str, spec: DeviceSpec) -> None:
    if spec.link is None or robot.sensors.flex is None:
        raise ValueError(f"devices.{name}: a link board needs its link and a sensors.flex section")


# the order of the twin's streams and of the rows in a window (the order its messages are written in): as
# before kinds were registered, so the files did not change with the registry
DYNAMIXEL = DeviceKind(
    name="dynamixel",
    role="joints",
    source=f"{_SOURCES}:ServoSource",
    topics=_dynamixel_topics,
    stamps={T.SERVO_STATE: "tick_ms"},
    timeline={T.SERVO_STATE: ("servo_", ("position", "velocity", "current"))},
    polled=frozenset({T.SERVO_STATE}),
    emulator=f"{_TWIN}:servo_bus_emulator",
    ceiling="acquisition.devices.bus_budget:servo_bus_ceiling_hz",
    resolution_rad=dx.RAD_PER_POSITION_COUNT,  # Present/Goal Position: 4096 counts a turn
    streams=((0, f"{_TWIN}:servo_streams"),),
    rows=((0, f"{_ROWS}:servo_rows"),),
)
PRESSURE_BOARD = DeviceKind(
    name="vslab_pressure_board",
    role="pressure",
    source=f"{_SOURCES}:PressureSource",
    topics=_pressure_topics,
    stamps={T.PRESSURE: "micros"},
    timeline={T.PRESSURE: ("", ("pressure",))},
    emulator=f"{_TWIN}:pressure_board_emulator",
    streams=((1, f"{_TWIN}:pressure_streams"),),
    rows=((3, f"{_ROWS}:pressure_rows"),),
)
STEPPER_BOARD = DeviceKind(
    name="vslab_stepper_board",
    role="stepper",
    source=f"{_SOURCES}:StepperSource",
    topics=_stepper_topics,
    stamps={T.STEPPER: "micros"},
    timeline={T.STEPPER: ("stepper_", ("position",))},
    emulator=f"{_TWIN}:stepper_board_emulator",
    streams=((2, f"{_TWIN}:stepper_streams"),),
    rows=((4, f"{_ROWS}:stepper_rows"),),
)
AURORA = DeviceKind(
    name="ndi_aurora",
    role="tracker",
    source=f"{_SOURCES}:TrackerSource",
    topics=_tracker_topics,
    stamps={T.TRACKER: "frame"},
    emulator=f"{_TWIN}:aurora_emulator",
    ceiling="acquisition.devices.bus_budget:tracker_ceiling_hz",
    streams=((3, f"{_TWIN}:tracker_streams"),),
    rows=((5, f"{_ROWS}:tracker_rows"),),
)
POPUP_CAN = DeviceKind(
    name="popup_can",
    role="joints",  # the CiA 402 joint drives (and the boards on the same bus)
    source="acquisition.recorder.can_source:PopupCanSource",
    topics=_can_topics,
    # the drives answer SYNC with position, velocity and torque: the host stamps them when the answers
    # arrive, ≈ 1 ms after the SYNC they sample at
    timeline={T.JOINT_STATE: ("servo_", ("position", "velocity", "torque"))},
    polled=frozenset({T.JOINT_STATE}),
    emulator=f"{_TWIN}:can_bus_emulator",
    streams=((5, f"{_TWIN}:drive_streams"),),
    rows=((1, f"{_ROWS}:drive_rows"),),
)
POPUP_MAIN_BOARD = DeviceKind(
    name="popup_main_board",
    role="pressure",  # link pressures and valves, over CAN
    topics=_pressure_topics,
    stamps={T.PRESSURE: "micros"},
    timeline={T.PRESSURE: ("", ("pressure",))},
    emulator=f"{_TWIN}:main_board_node",
    streams=((1, f"{_TWIN}:pressure_streams"),),
    rows=((3, f"{_ROWS}:pressure_rows"),),
)
POPUP_LINK_BOARD = DeviceKind(
    name="popup_link_board",
    role="link",  # a link's IMU and flex sensors, over CAN; one of them may carry the tip accelerometer
    topics=_link_board_topics,
    stamps={T.ACCEL: "micros"},
    emulator=f"{_TWIN}:link_board_node",
    streams=((4, f"{_TWIN}:accelerometer_streams"), (6, f"{_TWIN}:link_board_streams")),
    rows=((2, f"{_ROWS}:link_board_rows"), (6, f"{_ROWS}:accelerometer_rows")),
    check=_check_link_board,
)
