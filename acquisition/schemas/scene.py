"""The arm as Foxglove and ROS tools see it: standard topics made from a session's measured streams.

- ``/robot_description`` (``std_msgs/String``, once) and the URDF as an attachment (``robot.urdf``);
- ``/tf`` (``tf2_msgs/TFMessage``): every movable joint's child link in its parent, from the measured joint
  angles (virtual joints at 0: the rigid arm the joints command; the tracked tip shows where the soft arm is);
- ``/tf_static``: the fixed tool joint, and ``tracker → base_link`` when the registration is known;
- ``/joint_states`` (``sensor_msgs/JointState``): the actuated joints' angles, velocities and torques;
- ``/tracker/tip`` (``geometry_msgs/PoseStamped`` in the ``tracker`` frame): the tracked tip.

The fixed-layout topics stay as they are (the pipeline's fast path); these are derived from them, decimated
to ``rate_hz`` per topic (the tracker's frames are all kept).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from acquisition.devices.kinds import device_of
from acquisition.schemas import topics as T
from acquisition.schemas.standard import (
    STRING_SCHEMA,
    StandardMessage,
    fill_transforms,
    joint_state_message,
    pose_stamped_message,
    string_payload,
    transforms_message,
)
from models.robot import RobotDescription
from models.urdf import BASE, TOOL, JointTransforms, joint_origins, link_name, robot_urdf

TF, TF_STATIC = "/tf", "/tf_static"
JOINT_STATES = "/joint_states"
TIP_POSE = "/tracker/tip"
ROBOT_DESCRIPTION = "/robot_description"
TRACKER_FRAME = "tracker"
URDF_ATTACHMENT = "robot.urdf"
RATE_HZ = 50.0  # /tf and /joint_states: smooth in the 3D panel, a few % of a session's bytes
# derived from the measured topics: the pipeline reads the measured ones and leaves these out
STANDARD_TOPICS = frozenset({TF, TF_STATIC, JOINT_STATES, TIP_POSE, ROBOT_DESCRIPTION})


@dataclass
class Batch:
    """Messages of one standard topic: log times (ns) and payloads (n, size) bytes or a list of bytes."""

    topic: str
    schema_name: str
    schema_text: str
    log_time: np.ndarray
    payloads: np.ndarray | list[bytes] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.log_time)


class Scene:
    """The standard topics of one robot (and its tracker registration, a 4×4 base → tracker, if known)."""

    def __init__(self, robot: RobotDescription, base_to_tracker: np.ndarray | None = None) -> None:
        self.robot = robot
        self.urdf = robot_urdf(robot)
        rows = robot.dh_rows()
        frames = [BASE, *(link_name(r.joint) for r in rows)]
        self.tf = transforms_message(list(pairwise(frames)))
        static = [(frames[-1], TOOL)] + ([(TRACKER_FRAME, BASE)] if base_to_tracker is not None else [])
        self.tf_static = transforms_message(static)
        self._static = [joint_origins(robot)[-1]] + ([np.asarray(base_to_tracker, float)]
                                                    if base_to_tracker is not None else [])  # fmt: skip
        joints = T.joint_state_topic(robot)
        self._effort = joints == T.JOINT_STATE  # CiA 402 drives report torque; the servos a current
        self.joint_states = joint_state_message(robot.actuated_joints, effort=self._effort)
        self.tip = pose_stamped_message(TRACKER_FRAME)
        self._transforms = JointTransforms(robot)

    def schemas(self) -> dict[str, tuple[str, str]]:
        """Each standard topic's (schema name, ros2msg text)."""
        return {
            ROBOT_DESCRIPTION: ("std_msgs/msg/String", STRING_SCHEMA),
            **{topic: (m.schema_name, m.schema_text) for topic, m in (
                (TF_STATIC, self.tf_static), (TF, self.tf), (JOINT_STATES, self.joint_states),
                (TIP_POSE, self.tip))},
        }  # fmt: skip

    # ------------------------------------------------------------------------------------- batches
    def static(self, log_time_ns: int) -> list[Batch]:
        """What a session says once, at its start: the URDF and the fixed transforms."""
        t = np.array([log_time_ns], np.int64)
        rows = self.tf_static.empty(t)
        fill_transforms(rows, np.stack(self._static)[None])
        return [
            Batch(ROBOT_DESCRIPTION, "std_msgs/msg/String", STRING_SCHEMA, t, [string_payload(self.urdf)]),
            self._batch(TF_STATIC, self.tf_static, t, rows),
        ]

    def joints(self, log_time: np.ndarray, q: np.ndarray, velocity: np.ndarray | None = None,
               effort: np.ndarray | None = None) -> list[Batch]:  # fmt: skip
        """``/tf`` and ``/joint_states`` of joint angles q (n, A) in the robot's joint order at ``log_time``
        (rows with an unknown angle are left out; :class:`SceneStream` decimates)."""
        log_time = np.asarray(log_time, np.int64)
        pick = np.flatnonzero(np.isfinite(q).all(axis=1))
        t, q = log_time[pick], np.asarray(q, float)[pick]
        tf = self.tf.empty(t)
        fill_transforms(tf, self._transforms(q))
        js = self.joint_states.empty(t)
        columns = {"position": q, "velocity": _picked(velocity, pick, q.shape)}
        if self._effort:
            columns["effort"] = _picked(effort, pick, q.shape)
        for name, values in columns.items():
            for i in range(q.shape[1]):
                js[f"{name}{i}"] = values[:, i]
        return [self._batch(TF, self.tf, t, tf), self._batch(JOINT_STATES, self.joint_states, t, js)]

    def tracker(self, log_time: np.ndarray, rows: np.ndarray) -> list[Batch]:
        """``/tracker/tip`` of the tracker's frames (``TrackerPose`` rows) that have a pose."""
        seen = ~rows["missing"] & np.isfinite(rows["position"]).all(axis=1)
        t = np.asarray(log_time, np.int64)[seen]
        pose = self.tip.empty(t)
        for j, axis in enumerate("xyz"):
            pose[f"p_{axis}"] = rows["position"][seen, j]
        for j, axis in enumerate("wxyz"):  # the tracker says w x y z, ROS x y z w
            pose[f"q_{axis}"] = rows["quaternion"][seen, j]
        return [self._batch(TIP_POSE, self.tip, t, pose)]

    @staticmethod
    def _batch(topic: str, message: StandardMessage, t: np.ndarray, rows: np.ndarray) -> Batch:
        return Batch(topic, message.schema_name, message.schema_text, t, message.payloads(rows))


def _picked(values: np.ndarray | None, pick: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    return np.full(shape, np.nan) if values is None else np.asarray(values, float)[pick]


def joint_angles(robot: RobotDescription, streams: Mapping[str, object]) -> tuple[np.ndarray, ...]:
    """(log_time, q, velocity, effort) at each joint-state sample of a session's fixed topics (``TopicData``
    by topic): servo or drive columns in the robot's joint order, a stepper's angle held from its latest
    report (NaN before the first). Velocity and effort NaN where a joint does not report them."""
    names = robot.actuated_joints
    topic = T.joint_state_topic(robot)
    joints = device_of(robot, "joints")
    servo_ids = list(robot.devices[joints].ids) if joints else []
    servos = [names.index(n) for n in servo_ids if n in names]
    steppers = [k for k, j in enumerate(robot.joints) if j.drive == "stepper"]
    data = streams.get(topic) if topic else None
    stepper = streams.get(T.STEPPER) if steppers else None
    clock = data if data is not None and len(data) else stepper
    if clock is None or not len(clock):
        empty = np.zeros((0, len(names)))
        return np.zeros(0, np.int64), empty, empty, empty
    t = np.asarray(clock.log_time, np.int64)
    q, velocity, effort = (np.full((len(t), len(names)), np.nan) for _ in range(3))
    if data is not None and len(data) and servos:
        rows = data.rows
        q[:, servos] = rows["position"][:, : len(servos)]
        velocity[:, servos] = rows["velocity"][:, : len(servos)]
        if "torque" in rows.dtype.names:
            effort[:, servos] = rows["torque"][:, : len(servos)]
    if stepper is not None and len(stepper):
        k = np.searchsorted(np.asarray(stepper.log_time, np.int64), t, side="right") - 1
        held = stepper.rows["position"][np.clip(k, 0, None), : len(steppers)]
        q[:, steppers] = np.where((k >= 0)[:, None], held, np.nan)
    return t, q, velocity, effort


class SceneStream:
    """The standard topics of a recording as it is written: ``feed`` each fixed-topic batch in the order the
    writer gets them, write what it returns; ``finish`` at the end. ``/tf`` and ``/joint_states`` are
    decimated to ``rate_hz`` across batches. A robot with a stepper joint waits (up to ``max_wait_s``) for a
    stepper report at or after a joint sample before it places that sample, so the angle it holds is the one
    the file holds at that time, whatever order the batches come in. The messages come out ``batch_s`` of
    samples at a time (a recorder writes many small batches: each costs its numpy calls, whatever its size);
    ``finish`` gives the rest."""

    def __init__(self, scene: Scene, rate_hz: float = RATE_HZ, max_wait_s: float = 2.0,
                 batch_s: float = 0.5, stepper_history: int | None = 1024) -> None:  # fmt: skip
        self.scene = scene
        self.rate_hz = rate_hz
        self.max_wait_ns = int(max_wait_s * 1e9)
        self.batch_ns = int(batch_s * 1e9)
        self.stepper_history = stepper_history  # reports kept to hold angles from (None: all of them)
        self._tracker: list[_Rows] = []  # frames not yet turned into /tracker/tip
        self._next_place_ns: int | None = None  # joint samples are placed once the stream reaches it
        self.joint_topic = T.joint_state_topic(scene.robot)
        self.has_stepper = any(j.drive == "stepper" for j in scene.robot.joints)
        self._last_bucket: int | None = None
        self._pending: list[_Rows] = []  # joint samples waiting for the stepper
        self._stepper: _Rows | None = None  # its reports so far (the latest few)

    def feed(self, topic: str, log_time: np.ndarray, rows: np.ndarray) -> list[Batch]:
        log_time = np.asarray(log_time, np.int64)
        if not len(log_time):
            return []
        if topic == T.TRACKER:
            self._tracker.append(_Rows(log_time, rows))
            return self._tracker_tips() if _span(self._tracker) >= self.batch_ns else []
        if topic == T.STEPPER:
            self._stepper = (
                _Rows(log_time, rows)
                if self._stepper is None
                else self._stepper.tail(log_time, rows, self._stepper_kept(log_time))
            )
        elif topic == self.joint_topic:
            keep = self._decimate(log_time)
            if len(keep):
                self._pending.append(_Rows(log_time[keep], rows[keep]))
        else:
            return []
        newest = int(log_time.max())
        if self._next_place_ns is None:
            self._next_place_ns = newest + self.batch_ns
        if not self._pending or newest < self._next_place_ns:  # at most once per batch_s of samples
            return []
        self._next_place_ns = newest + self.batch_ns
        if not self.has_stepper:
            return self._place(None)
        return self._place(int(self._stepper.log_time[-1]) if self._stepper is not None else None, newest)

    def _stepper_kept(self, log_time: np.ndarray) -> int | None:
        """How many stepper reports to keep: ``stepper_history``, and at least those that hold the pending
        joint samples' angles (from the last report before the oldest of them on)."""
        if self.stepper_history is None or not self._pending:
            return self.stepper_history
        oldest = min(int(p.log_time.min()) for p in self._pending)
        times = np.concatenate([self._stepper.log_time, log_time])
        return max(
            self.stepper_history, len(times) - max(0, int(np.searchsorted(times, oldest, "right")) - 1)
        )

    def finish(self) -> list[Batch]:
        """Whatever is still held back: joint samples placed with the stepper's latest report, frames."""
        return self._place(None) + self._tracker_tips()

    def _tracker_tips(self) -> list[Batch]:
        if not self._tracker:
            return []
        frames, self._tracker = self._tracker, []
        return self.scene.tracker(np.concatenate([f.log_time for f in frames]),
                                  np.concatenate([f.rows for f in frames]))  # fmt: skip

    def _decimate(self, log_time: np.ndarray) -> np.ndarray:
        bucket = log_time // int(1e9 / self.rate_hz)
        first = np.ones(len(bucket), bool)
        first[1:] = bucket[1:] != bucket[:-1]
        if self._last_bucket is not None:
            first &= bucket > self._last_bucket
        newest = int(bucket.max())
        self._last_bucket = newest if self._last_bucket is None else max(self._last_bucket, newest)
        return np.flatnonzero(first)

    def _place(self, until: int | None, newest: int | None = None) -> list[Batch]:
        """/tf and /joint_states of the pending joint samples up to ``until`` (None: all of them; also those
        older than ``max_wait_s`` before ``newest``)."""
        if not self._pending:
            return []
        pending = _Rows(np.concatenate([p.log_time for p in self._pending]),
                        np.concatenate([p.rows for p in self._pending]))  # fmt: skip
        if until is None and newest is None:
            ready = np.ones(len(pending), bool)
        else:
            limit = max(until if until is not None else -1, (newest or 0) - self.max_wait_ns)
            ready = pending.log_time <= limit
        if not ready.any():
            return []
        self._pending = [] if ready.all() else [_Rows(pending.log_time[~ready], pending.rows[~ready])]
        streams = {self.joint_topic: _Rows(pending.log_time[ready], pending.rows[ready])}
        if self._stepper is not None:
            streams[T.STEPPER] = self._stepper
        t, q, velocity, effort = joint_angles(self.scene.robot, streams)
        return self.scene.joints(t, q, velocity, effort)


def _span(batches: list[_Rows]) -> int:
    """ns from the first held sample to the last (-1 when none is held)."""
    return int(batches[-1].log_time[-1] - batches[0].log_time[0]) if batches else -1


@dataclass
class _Rows:
    """Some rows of a topic, as :func:`joint_angles` reads them."""

    log_time: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)

    def tail(self, log_time: np.ndarray, rows: np.ndarray, keep: int | None) -> _Rows:
        """These rows and the new ones, the latest ``keep`` (None: all; a stepper's reports: what holds its
        angle)."""
        first = -keep if keep is not None else 0
        return _Rows(
            np.concatenate([self.log_time, log_time])[first:], np.concatenate([self.rows, rows])[first:]
        )
