"""The standard ROS 2 messages tools understand (``tf2_msgs/TFMessage``, ``geometry_msgs/PoseStamped``,
``sensor_msgs/JointState``, ``std_msgs/String``), encoded in CDR in bulk.

These messages hold strings (frame ids, joint names), so they are not fixed-layout ros2msg in general. But
a topic's strings never change (its frames, its joints), so every message of one topic has the same bytes but
for its numbers: one template message, and a structured dtype whose fields sit at the numbers' offsets. A
batch is the template repeated and the numbers filled column by column, as the fixed-layout topics are
(``acquisition.schemas.cdr``). mcap-ros2-support's generic decoder reads the same bytes (the tests' oracle).

CDR (XCDR1, little-endian): a 4-byte encapsulation header, then each primitive aligned to its size counted
from the header's end; a string is a uint32 length (its NUL included), its bytes and a NUL; a sequence is a
uint32 count and its elements.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from acquisition.schemas.cdr import CDR_LE_HEADER, SchemaError

_SEPARATOR = "=" * 80

_TIME = "builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"
_HEADER = "std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"
_VECTOR3 = "geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"
_POINT = "geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION = "geometry_msgs/Quaternion", "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_TRANSFORM = "geometry_msgs/Transform", "Vector3 translation\nQuaternion rotation\n"
_TRANSFORM_STAMPED = (
    "geometry_msgs/TransformStamped",
    "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
)
_POSE = "geometry_msgs/Pose", "Point position\nQuaternion orientation\n"


def _schema(root: str, dependencies: Sequence[tuple[str, str]]) -> str:
    """A ros2msg schema as MCAP stores it: the root definition, then each dependency after a separator."""
    return root + "".join(f"{_SEPARATOR}\nMSG: {name}\n{text}" for name, text in dependencies)


TF_SCHEMA = _schema(
    "geometry_msgs/TransformStamped[] transforms\n",
    [_TRANSFORM_STAMPED, _HEADER, _TIME, _TRANSFORM, _VECTOR3, _QUATERNION],
)
POSE_STAMPED_SCHEMA = _schema(
    "std_msgs/Header header\nPose pose\n", [_HEADER, _TIME, _POSE, _POINT, _QUATERNION]
)
JOINT_STATE_SCHEMA = _schema(
    "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
    [_HEADER, _TIME],
)
STRING_SCHEMA = "string data\n"


class _Builder:
    """One CDR message, written field by field; numeric fields become named slots of the batch dtype."""

    def __init__(self) -> None:
        self.buf = bytearray()
        self.slots: list[tuple[str, str, int]] = []  # (field name, numpy type, offset in the payload)

    def _align(self, size: int) -> None:
        self.buf += bytes(-len(self.buf) % size)

    def u32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", value)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.u32(len(data))
        self.buf += data

    def slot(self, name: str, kind: str) -> None:
        size = np.dtype(kind).itemsize
        self._align(size)
        self.slots.append((name, kind, len(CDR_LE_HEADER) + len(self.buf)))
        self.buf += bytes(size)

    def stamp(self, frame_id: str, prefix: str = "") -> None:
        self.slot(f"{prefix}sec", "<i4")
        self.slot(f"{prefix}nanosec", "<u4")
        self.string(frame_id)

    def float64s(self, prefix: str, names: str) -> None:
        for axis in names:
            self.slot(f"{prefix}{axis}", "<f8")


@dataclass(frozen=True)
class StandardMessage:
    """One topic's messages: a schema, a template payload and the dtype of its numbers' slots."""

    schema_name: str
    schema_text: str
    template: bytes
    dtype: np.dtype

    @classmethod
    def _from(cls, name: str, schema: str, builder: _Builder) -> StandardMessage:
        payload = CDR_LE_HEADER + bytes(builder.buf)
        names, kinds, offsets = zip(*builder.slots, strict=True) if builder.slots else ((), (), ())
        dtype = np.dtype({"names": list(names), "formats": list(kinds), "offsets": list(offsets),
                          "itemsize": len(payload)})  # fmt: skip
        return cls(name, schema, payload, dtype)

    @property
    def size(self) -> int:
        return len(self.template)

    def empty(self, log_time_ns: np.ndarray) -> np.ndarray:
        """``n`` messages as the template, stamped with ``log_time_ns``; fill the other fields by name."""
        t = np.asarray(log_time_ns, dtype=np.int64)
        rows = np.zeros(len(t), self.dtype)
        for name in self.dtype.names:
            if name.endswith("sec") and not name.endswith("nanosec"):
                rows[name] = t // 1_000_000_000
            elif name.endswith("nanosec"):
                rows[name] = t % 1_000_000_000
        return rows

    def payloads(self, rows: np.ndarray) -> np.ndarray:
        """The encoded messages, (n, size) bytes: the template with the rows' numbers written in. (Field by
        field: numpy copies a structured array's fields, not the bytes between them.)"""
        raw = np.frombuffer(self.template * len(rows), np.uint8).reshape(len(rows), self.size).copy()
        out = raw.view(self.dtype).reshape(len(rows))
        for name in self.dtype.names:
            out[name] = rows[name]
        return raw


def transforms_message(pairs: Sequence[tuple[str, str]]) -> StandardMessage:
    """``tf2_msgs/msg/TFMessage`` of one transform per (parent, child) frame pair; slot names ``t<i>_x`` …
    (translation x y z), ``r<i>_x`` … (rotation x y z w)."""
    b = _Builder()
    b.u32(len(pairs))
    for i, (parent, child) in enumerate(pairs):
        b.stamp(parent, f"h{i}_")
        b.string(child)
        b.float64s(f"t{i}_", "xyz")
        b.float64s(f"r{i}_", "xyzw")
    return StandardMessage._from("tf2_msgs/msg/TFMessage", TF_SCHEMA, b)


def pose_stamped_message(frame_id: str) -> StandardMessage:
    """``geometry_msgs/msg/PoseStamped``: slots ``p_x p_y p_z`` and ``q_x q_y q_z q_w``."""
    b = _Builder()
    b.stamp(frame_id)
    b.float64s("p_", "xyz")
    b.float64s("q_", "xyzw")
    return StandardMessage._from("geometry_msgs/msg/PoseStamped", POSE_STAMPED_SCHEMA, b)


def joint_state_message(names: Sequence[str], effort: bool = True) -> StandardMessage:
    """``sensor_msgs/msg/JointState`` of ``names``: slots ``position<i>``, ``velocity<i>``, ``effort<i>``
    (no effort: an empty sequence, as ROS does for a joint that does not report it)."""
    b = _Builder()
    b.stamp("")
    b.u32(len(names))
    for name in names:
        b.string(name)
    for field in ("position", "velocity", *(["effort"] if effort else [])):
        b.u32(len(names))
        for i in range(len(names)):
            b.slot(f"{field}{i}", "<f8")
    if not effort:
        b.u32(0)
    return StandardMessage._from("sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA, b)


def string_payload(text: str) -> bytes:
    """One ``std_msgs/msg/String``."""
    b = _Builder()
    b.string(text)
    return CDR_LE_HEADER + bytes(b.buf)


def fill_transforms(rows: np.ndarray, transforms: np.ndarray) -> None:
    """Write (n, k, 4, 4) homogeneous transforms into the rows of a :func:`transforms_message`."""
    k = transforms.shape[1]
    quaternion = quaternions(transforms[..., :3, :3])
    if f"t{k - 1}_x" not in (rows.dtype.names or ()) or f"t{k}_x" in rows.dtype.names:
        raise SchemaError(f"{k} transforms for a TFMessage of another size")
    for i in range(k):
        for j, axis in enumerate("xyz"):
            rows[f"t{i}_{axis}"] = transforms[:, i, j, 3]
        for j, axis in enumerate("xyzw"):
            rows[f"r{i}_{axis}"] = quaternion[:, i, j]


def quaternions(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as x y z w of rotation matrices (..., 3, 3): Shepperd's method (the
    largest of w, x, y, z taken from the diagonal, the others from the off-diagonal sums), vectorised. What
    scipy's ``Rotation.from_matrix`` gives for proper rotations, without its per-call cost at every batch."""
    m = rotation
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    trace = m00 + m11 + m22
    pick = np.argmax(np.stack([trace, m00, m11, m22]), axis=0)
    big = np.sqrt(np.maximum(1.0 + np.choose(pick, [trace, m00 - m11 - m22, m11 - m00 - m22,
                                                    m22 - m00 - m11]), 1e-300))  # fmt: skip
    half = 0.5 * big  # the largest component
    inv = 0.5 / big
    candidates = np.stack([
        np.stack([d21 * inv, d02 * inv, d10 * inv, half], -1),  # w largest
        np.stack([half, s01 * inv, s02 * inv, d21 * inv], -1),  # x largest
        np.stack([s01 * inv, half, s12 * inv, d02 * inv], -1),  # y largest
        np.stack([s02 * inv, s12 * inv, half, d10 * inv], -1),  # z largest
    ])  # fmt: skip
    q = np.take_along_axis(candidates, pick[None, ..., None], axis=0)[0]
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
