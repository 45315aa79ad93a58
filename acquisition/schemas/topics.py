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
    """Every topic a session of ``robot`` may write, by topic name."""
    servo_dev = robot.devices.get("servo_bus") or robot.devices.get("main_board")
    servos = [n for n in (servo_dev.ids if servo_dev else {}) if _drive(robot, n) != "stepper"]
    steppers = [j.name for j in robot.joints if j.drive == "stepper"]
    c = robot.pneumatics.channels
    messages: dict[str, FixedMessage | None] = {
        SERVO_STATE: servo_state(len(servos)) if servos else None,
        SERVO_GOAL: servo_goal(len(servos)) if servos else None,
        PRESSURE: pressure(c),
        PRESSURE_COMMAND: pressure_command(c),
        STEPPER: stepper(len(steppers)) if steppers else None,
        TRACKER: TRACKER_POSE,
        ACCEL: ACCELERATION,
        EVENTS: None,
    }
    return {name: Topic(name, msg) for name, msg in messages.items() if msg is not None or name == EVENTS}


def _drive(robot: RobotDescription, joint: str) -> str | None:
    return next((j.drive for j in robot.joints if j.name == joint), None)
