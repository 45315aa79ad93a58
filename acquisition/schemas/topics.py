"""The topics of a session and their message layouts: the contract between the recorder and the pipeline.

Every sample is one message on its device's topic. ``log_time`` is the host receive time (ns, the recording
PC's clock); the payload holds the device's own stamp (a wrapping counter in device ticks) and its sequence or
frame number, so the pipeline can fit each device clock to host time. Values are SI; the pressure topic also
keeps the raw ADC counts because their calibration belongs to the pipeline, not to the recorder.

Array lengths follow the robot (how many servos, pressure channels, steppers): the schema text stored in each
file says them, so a file always describes itself.
"""

from __future__ import annotations

from dataclasses import dataclass

from acquisition.devices.kinds import device_kinds, device_of, kind_of
from acquisition.schemas.cdr import Field, FixedMessage
from acquisition.schemas.events import EVENT_SCHEMA, EVENT_SCHEMA_NAME, EVENTS
from models.robot import RobotDescription

SERVO_STATE = "/servo/state"
SERVO_GOAL = "/servo/goal"
PRESSURE = "/pressure/measured"
PRESSURE_COMMAND = "/pressure/command"
STEPPER = "/stepper/state"
TRACKER = "/tracker/pose"
ACCEL = "/imu/accel"
JOINT_STATE = "/joint/state"


def link_orientation_topic(link: str) -> str:
    """The topic of the orientation of ``link``'s end (its board's IMU)."""
    return f"/{link}/orientation"


def link_flex_topic(link: str) -> str:
    """The topic of ``link``'s four flex sensors."""
    return f"/{link}/flex"


MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"


def _board_sample(what: str) -> tuple[Field, Field]:
    """What a board's sample starts with: its number and the board's ``micros()`` stamp, the clock the
    pipeline fits to host time."""
    return Field("seq", "uint32", doc=what), Field("micros", "uint32", doc="board micros(), wraps at 2^32")


_COMMAND_SEQ = Field("seq", "uint32", doc="command number")


def servo_state(n: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/ServoState",
        (
            Field("seq", "uint32", doc="host poll number"),
            Field("tick_ms", "uint16", doc="servo Realtime Tick of the first servo, ms, wraps at 32768"),
            Field("position", "float64", n, "rad (encoder)"),
            Field("velocity", "float64", n, "rad/s"),
            Field("current", "float64", n, "A"),
            Field("moving", "bool", n),
        ),
        "One Sync Read of every servo on the bus (order: the robot's servo ids).",
    )


def joint_state(n: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/JointState",
        (
            Field(
                "seq",
                "uint32",
                doc="the SYNC the drives answered (host count; one every drive did not answer is a hole)",
            ),
            Field("position", "float64", n, "rad (drive encoder)"),
            Field("velocity", "float64", n, "rad/s"),
            Field("torque", "float64", n, "N·m (the drive's torque estimate)"),
            Field("statusword", "uint16", n, "CiA 402 statusword (0x6041)"),
        ),
        "What every CiA 402 joint drive answered to one SYNC (order: the robot's drive node ids).",
    )


def servo_goal(n: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/ServoGoal",
        (
            _COMMAND_SEQ,
            Field("position", "float64", n, "rad"),
            Field("profile_velocity", "float64", n, "rad/s, 0 = unlimited"),
            Field("profile_acceleration", "float64", n, "rad/s^2, 0 = unlimited"),
        ),
        "Goal positions written to the servos.",
    )


def pressure(c: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/Pressure",
        (
            *_board_sample("board sample number"),
            Field("counts", "int16", c, "ADS1115 counts per channel"),
            Field("pressure", "float64", c, "Pa (gauge), from the configured sensor chain"),
            Field("valve_open", "bool", c),
        ),
        "Link pressures measured by the pressure board.",
    )


def pressure_command(c: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/PressureCommand",
        (
            _COMMAND_SEQ,
            Field("setpoint", "float64", c, "Pa (gauge), regulator set-points"),
            Field("valve_open", "bool", c),
        ),
        "Regulator set-points and valve states sent to the pressure board.",
    )


def stepper(s: int) -> FixedMessage:
    return FixedMessage(
        "vslab_msgs/msg/StepperState",
        (
            *_board_sample("board report number"),
            Field("position_steps", "int32", s, "microsteps"),
            Field("position", "float64", s, "rad"),
            Field("moving", "bool"),
        ),
        "Base stepper position reports.",
    )


TRACKER_POSE = FixedMessage(
    "vslab_msgs/msg/TrackerPose",
    (
        Field("frame", "uint32", doc="tracker frame number (its clock: 40 Hz)"),
        Field("port_handle", "uint16"),
        Field("port_status", "uint16", doc="NDI port status bits (0x40: out of volume)"),
        Field("missing", "bool", doc="no pose this frame: position/quaternion/rms are NaN"),
        Field("position", "float64", 3, "m, tracker frame"),
        Field("quaternion", "float64", 4, "w x y z"),
        Field("rms_error", "float64", doc="m"),
    ),
    "Pose of one tracked tool (the tip coil) in the tracker's frame.",
)

ACCELERATION = FixedMessage(
    "vslab_msgs/msg/Acceleration",
    (
        *_board_sample("sample number"),
        Field("acceleration", "float64", 3, "m/s^2, sensor frame, gravity included"),
    ),
    "Accelerometer on the link under test (POPUP impact test).",
)


LINK_ORIENTATION = FixedMessage(
    "vslab_msgs/msg/LinkOrientation",
    (
        *_board_sample("the link board's sample number"),
        Field("rpy", "float64", 3, "rad: roll, pitch, yaw of the link's end frame in the base frame (ZYX)"),
    ),
    "Orientation of an inflatable link's end, from its board's IMU.",
)

LINK_FLEX = FixedMessage(
    "vslab_msgs/msg/LinkFlex",
    (
        *_board_sample("the link board's sample number"),
        Field("counts", "uint16", 4, "12-bit ADC counts of the flex sensors at 0, 90, 180, 270 deg"),
    ),
    "The four flex sensors around an inflatable link.",
)


@dataclass(frozen=True)
class Topic:
    name: str
    message: FixedMessage | None  # None: the events topic (variable size)

    @property
    def schema_name(self) -> str:
        return self.message.name if self.message else EVENT_SCHEMA_NAME

    @property
    def schema_text(self) -> str:
        return self.message.ros2msg if self.message else EVENT_SCHEMA


def session_topics(robot: RobotDescription) -> dict[str, Topic]:
    """Every topic a session of ``robot`` may write, by topic name: the standard ones (pressure, tracker,
    accelerometer, events: written by the twin's world whichever devices carry them) and those of each of its
    devices' kinds (:mod:`acquisition.devices.kinds`)."""
    joints = device_of(robot, "joints")
    joint_topics = kind_of(robot, joints).topics_of(robot, joints) if joints else {}
    c = robot.pneumatics.channels
    messages: dict[str, FixedMessage | None] = {
        SERVO_STATE: joint_topics.get(SERVO_STATE),
        JOINT_STATE: joint_topics.get(JOINT_STATE),
        SERVO_GOAL: joint_topics.get(SERVO_GOAL),
        PRESSURE: pressure(c),
        PRESSURE_COMMAND: pressure_command(c),
        STEPPER: None,
        TRACKER: TRACKER_POSE,
        ACCEL: ACCELERATION,
        EVENTS: None,
    }
    for name, kind in device_kinds(robot).items():
        for topic, message in kind.topics_of(robot, name).items():
            if messages.get(topic) is None:
                messages[topic] = message
    return {name: Topic(name, msg) for name, msg in messages.items() if msg is not None or name == EVENTS}


def joint_state_topic(robot: RobotDescription) -> str | None:
    """Where ``robot``'s joint angles are measured: the Dynamixel bus's Sync Reads (``/servo/state``) or the
    CiA 402 drives' answers to SYNC (``/joint/state``), as the joints device's kind writes them; None without
    a joints device."""
    joints = device_of(robot, "joints")
    if joints is None:
        return None
    return SERVO_STATE if SERVO_STATE in kind_of(robot, joints).topics_of(robot, joints) else JOINT_STATE
