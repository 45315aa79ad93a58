"""Sensor models: true SI values in, what the device would report out (quantised, noisy, in its units).

Dynamixel XM430 registers (devices.md), the pressure transducer + ADS1115 chain, and an NDI Aurora-like
tracker (pose of the tip coil in the field generator's frame, MISSING outside the field volume). Vectorised;
noise comes from the generator passed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.codecs import dynamixel as dx
from models.effects import TrackerDistortion, tracker_bias
from models.robot import PressureSensorSpec

# the XM430's register units live with the protocol; named here as the sensor model uses them
POSITION_COUNTS_PER_REV = dx.POSITION_COUNTS_PER_REV
CURRENT_A_PER_COUNT = dx.AMP_PER_CURRENT_UNIT
VELOCITY_RAD_S_PER_COUNT = dx.RAD_S_PER_VELOCITY_UNIT
CURRENT_LIMIT_COUNTS = dx.CURRENT_LIMIT_DEFAULT
ADC_MIN_COUNTS, ADC_MAX_COUNTS = -32768, 32767  # ADS1115 signed 16-bit output code

# NDI port status bits (devices.md)
PORT_OCCUPIED = 0x01
PORT_INITIALIZED = 0x10
PORT_ENABLED = 0x20
PORT_OUT_OF_VOLUME = 0x40


# ----------------------------------------------------------------------------------------- Dynamixel
def encoder_counts(angle_rad: np.ndarray, zero_count: int = 2048) -> np.ndarray:
    """Present Position counts of a joint angle (4096 per turn, ``zero_count`` at angle 0), nearest count."""
    return (
        np.rint(np.asarray(angle_rad) * POSITION_COUNTS_PER_REV / (2 * np.pi)).astype(np.int64) + zero_count
    )


def encoder_angle(counts: np.ndarray, zero_count: int = 2048) -> np.ndarray:
    """Joint angle (rad) of Present Position counts."""
    return (np.asarray(counts, dtype=float) - zero_count) * (2 * np.pi / POSITION_COUNTS_PER_REV)


def current_counts(current_a: np.ndarray, noise_counts_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Present Current counts (2.69 mA each) with Gaussian noise, clipped to the current limit."""
    counts = np.asarray(current_a) / CURRENT_A_PER_COUNT
    counts = (
        counts + rng.normal(0.0, noise_counts_sigma, size=counts.shape) if noise_counts_sigma > 0 else counts
    )
    return np.clip(np.rint(counts), -CURRENT_LIMIT_COUNTS, CURRENT_LIMIT_COUNTS).astype(np.int64)


def velocity_counts(
    velocity_rad_s: np.ndarray, rng: np.random.Generator | None = None, noise_counts_sigma: float = 0.0
) -> np.ndarray:
    """Present Velocity counts (0.229 rpm each), optionally noisy."""
    counts = np.asarray(velocity_rad_s) / VELOCITY_RAD_S_PER_COUNT
    if rng is not None and noise_counts_sigma > 0:
        counts = counts + rng.normal(0.0, noise_counts_sigma, size=counts.shape)
    return np.rint(counts).astype(np.int64)


def to_signed(raw: np.ndarray, nbytes: int) -> np.ndarray:
    """Signed int64 of an unsigned ``nbytes`` register read (the SDK returns signed items as unsigned)."""
    if nbytes not in (1, 2, 4):
        raise ValueError(f"nbytes must be 1, 2 or 4, got {nbytes}")
    raw = np.asarray(raw, dtype=np.int64)
    bits = 8 * nbytes
    if np.any((raw < 0) | (raw >= 1 << bits)):
        raise ValueError(f"raw register values must be unsigned {bits}-bit")
    return np.where(raw >= 1 << (bits - 1), raw - (1 << bits), raw)


# ------------------------------------------------------------------------------ pressure transducer
def pressure_to_adc_counts(
    pressure_pa: np.ndarray, spec: PressureSensorSpec, rng: np.random.Generator
) -> np.ndarray:
    """ADS1115 counts (int64) of a gauge pressure: the configured transducer line (range clipped), voltage
    noise, nearest LSB, then the ADC's own saturation (at ±4.096 V gain a 4.5 V output clips at 32767).
    The way back is the robot description's ``PressureSensorSpec.counts_to_pa``."""
    volts = spec.pa_to_volts(pressure_pa)
    if spec.adc_noise_v > 0:
        volts = volts + rng.normal(0.0, spec.adc_noise_v, size=volts.shape)
    return np.clip(np.rint(volts / spec.adc_lsb_v), ADC_MIN_COUNTS, ADC_MAX_COUNTS).astype(np.int64)


# ----------------------------------------------------------------------------------- accelerometer
def accelerometer_reading(
    specific_force_m_s2: np.ndarray,
    lsb_m_s2: float,
    full_scale_m_s2: float,
    noise_rms_m_s2: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """What a MEMS accelerometer reports (m/s², (..., 3)) for a true specific force in its frame: white noise
    of ``noise_rms_m_s2`` per axis, rounded to the LSB, saturating at ± full scale."""
    f = np.asarray(specific_force_m_s2, dtype=float)
    if noise_rms_m_s2 > 0:
        f = f + rng.normal(0.0, noise_rms_m_s2, size=f.shape)
    limit = np.floor(full_scale_m_s2 / lsb_m_s2)
    return np.clip(np.rint(f / lsb_m_s2), -limit, limit) * lsb_m_s2


# ------------------------------------------------------------------------------ link boards (POPUP)
FLEX_ANGLES_RAD = np.deg2rad([0.0, 90.0, 180.0, 270.0])  # the four flex sensors around a link's axis


def flex_counts(bend_rad: np.ndarray, spec, rng: np.random.Generator) -> np.ndarray:
    """The four flex sensors' ADC counts (..., 4) of links bent by their two virtual joints ``bend_rad``
    (..., 2): sensor i reads κ_i = δ_a cos φ_i + δ_b sin φ_i (``FlexSensorSpec``)."""
    bend = np.asarray(bend_rad, dtype=float)
    kappa = bend[..., :1] * np.cos(FLEX_ANGLES_RAD) + bend[..., 1:2] * np.sin(FLEX_ANGLES_RAD)
    counts = spec.counts_straight + spec.counts_per_rad * kappa
    if spec.noise_counts > 0:
        counts = counts + rng.normal(0.0, spec.noise_counts, size=counts.shape)
    return np.clip(np.rint(counts), 0, spec.adc_max_counts).astype(np.int64)


def rpy_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) (..., 3) of rotations R = Rz(yaw) Ry(pitch) Rx(roll) (the inverse of
    :func:`rotation_from_rpy`): what an IMU's attitude filter reports."""
    r = np.asarray(rotation, dtype=float)
    roll = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    pitch = -np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


# --------------------------------------------------------------------------------------- rotations
def rotation_from_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) · Ry(pitch) · Rx(roll), shape (..., 3, 3) for broadcast angle arrays (rad)."""
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (roll, pitch, yaw)))
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) with p' = R p + t, from R (..., 3, 3) and t (..., 3)."""
    rotation, translation = np.asarray(rotation, dtype=float), np.asarray(translation, dtype=float)
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros((*batch, 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (q0, qx, qy, qz), q0 ≥ 0, of rotation matrices (..., 3, 3) (Shepperd's method)."""
    rot = np.asarray(rot, dtype=float)
    m00, m11, m22 = rot[..., 0, 0], rot[..., 1, 1], rot[..., 2, 2]
    trace = m00 + m11 + m22
    # four candidate formulas; pick the best-conditioned per matrix
    cand = np.stack(
        [
            np.stack([1 + trace, rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0],
                      rot[..., 1, 0] - rot[..., 0, 1]], -1),
            np.stack([rot[..., 2, 1] - rot[..., 1, 2], 1 + m00 - m11 - m22, rot[..., 0, 1] + rot[..., 1, 0],
                      rot[..., 0, 2] + rot[..., 2, 0]], -1),
            np.stack([rot[..., 0, 2] - rot[..., 2, 0], rot[..., 0, 1] + rot[..., 1, 0], 1 - m00 + m11 - m22,
                      rot[..., 1, 2] + rot[..., 2, 1]], -1),
            np.stack([rot[..., 1, 0] - rot[..., 0, 1], rot[..., 0, 2] + rot[..., 2, 0],
                      rot[..., 1, 2] + rot[..., 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )  # fmt: skip
    best = np.argmax(np.stack([trace, m00, m11, m22], -1), axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of (normalised) quaternions (q0, qx, qy, qz)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


# ------------------------------------------------------------------------------------------ tracker
@dataclass(frozen=True)
class TrackerSpec:
    """Where the field generator sits (4×4 base → tracker, p_t = R p_b + t), position noise per axis (m),
    field volume (axis-aligned box in tracker coordinates, m), the mean of the reported RMS error (mm) and the
    field's distortion (``models.effects``; None: an undistorted field)."""

    base_to_tracker: np.ndarray
    noise_m: float
    field_min_m: np.ndarray
    field_max_m: np.ndarray
    rms_error_mm_mean: float
    distortion: TrackerDistortion | None = None

    def __post_init__(self) -> None:
        for name in ("base_to_tracker", "field_min_m", "field_max_m"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float))
        if (
            self.base_to_tracker.shape != (4, 4)
            or self.field_min_m.shape != (3,)
            or self.field_max_m.shape != (3,)
        ):
            raise ValueError("base_to_tracker must be 4×4 and the field box corners 3-vectors")
        if np.any(self.field_min_m >= self.field_max_m) or self.noise_m < 0:
            raise ValueError("field_min_m must be below field_max_m on every axis and noise_m ≥ 0")


@dataclass(frozen=True)
class TrackerReading:
    """What the tracker reports per sample (TX/BX fields); a MISSING sample carries NaN, never a zero pose."""

    position_m: np.ndarray  # (..., 3) tracker frame; NaN when missing
    quaternion: np.ndarray  # (..., 4) q0 qx qy qz; NaN when missing
    rms_error: np.ndarray  # (...,) mm as the Aurora reports it; NaN when missing
    missing: np.ndarray  # (...,) bool
    port_status: np.ndarray  # (...,) int NDI port status bits


def tracker_measurement(
    tip_pos_base: np.ndarray, tip_rot_base: np.ndarray, spec: TrackerSpec, rng: np.random.Generator
) -> TrackerReading:
    """The tip coil as the tracker reports it: pose in the tracker frame with the field's distortion bias and
    Gaussian position noise, MISSING (NaN pose, out-of-volume bit) when the true position is outside the field
    box. Takes tip positions (..., 3) and rotations (..., 3, 3) in the robot base frame."""
    rot, trans = spec.base_to_tracker[:3, :3], spec.base_to_tracker[:3, 3]
    pos = np.asarray(tip_pos_base) @ rot.T + trans
    missing = np.any((pos < spec.field_min_m) | (pos > spec.field_max_m), axis=-1)
    if spec.distortion is not None:
        pos = pos + tracker_bias(spec.distortion, pos)
    pos = pos + rng.normal(0.0, spec.noise_m, size=pos.shape)
    quat = rotation_to_quaternion(rot @ np.asarray(tip_rot_base))
    rms = np.abs(rng.normal(spec.rms_error_mm_mean, 0.1 * spec.rms_error_mm_mean, size=missing.shape))
    status = np.where(missing, PORT_OUT_OF_VOLUME, 0) | PORT_OCCUPIED | PORT_INITIALIZED | PORT_ENABLED
    return TrackerReading(
        position_m=np.where(missing[..., None], np.nan, pos),
        quaternion=np.where(missing[..., None], np.nan, quat),
        rms_error=np.where(missing, np.nan, rms),
        missing=missing,
        port_status=status.astype(np.int64),
    )
