"""What the devices report: the twin's true trace sampled at each device's own instants.

A device samples on its own clock (the pressure board's ADC conversions, the tracker's frames) or when the
host polls it (the servo bus). Each sample carries the device's stamp (wrapping counter), a sequence or frame
number, the host receive time (int64 ns, after USB latency and jitter) and the device's quantised, noisy
reading. Streams are column tables (dict of equal-length arrays) with a ``robot`` column for the batch index.
"""

from __future__ import annotations

import functools

import canopen
import numpy as np

from acquisition.codecs import popup_boards
from acquisition.devices.kinds import device_of
from models.robot import CAN_DIR, PressureSensorSpec, RobotDescription
from models.statics import servo_current_a
from twin import sensors
from twin.clocks import HostLinkSpec, SimulatedClocks, host_receive_ns
from twin.kernel import Trace
from twin.noise import BenchNoise, RowNoise

Stream = dict[str, np.ndarray]


def device_sample_instants(clocks: SimulatedClocks, period_s: float, t0: float, t1: float):
    """True times in (t0, t1] at which each robot's device fires at multiples of ``period_s`` of its own
    clock. Returns (robot index, sample number k, true time), all flat and ordered by robot then time."""
    rate = 1.0 + clocks.drift_ppm * 1e-6
    k0 = np.floor((rate * t0 + clocks.offset_s) / period_s).astype(np.int64) + 1
    k1 = np.floor((rate * t1 + clocks.offset_s) / period_s).astype(np.int64)
    counts = np.maximum(k1 - k0 + 1, 0)
    robot = np.repeat(np.arange(len(counts)), counts)
    k = np.repeat(k0, counts) + (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))
    t = (k * period_s - clocks.offset_s[robot]) / rate[robot]
    return robot, k, t


def host_poll_instants(batch: int, period_s: float, t0: float, t1: float):
    """Host-driven polling (e.g. Sync Read) on the host clock, taken as true time: same layout as above."""
    k = np.arange(np.floor(t0 / period_s) + 1, np.floor(t1 / period_s) + 1, dtype=np.int64)
    robot = np.repeat(np.arange(batch), len(k))
    kk = np.tile(k, batch)
    return robot, kk, kk * period_s


def _step_index(trace: Trace, t: np.ndarray, dt: float) -> np.ndarray:
    """The trace step whose state holds at true time t (the last step that ended at or before t)."""
    first = trace.t[0] - dt
    return np.clip(np.floor((t - first) / dt + 1e-9).astype(np.int64) - 1, 0, len(trace.t) - 1)


def _host(link, t: np.ndarray, rng: RowNoise) -> np.ndarray:
    spec = HostLinkSpec(latency_s=link.latency_s, jitter_s=link.jitter_s, kind=link.kind)
    return host_receive_ns(t, spec, rng)


def _stamped(device, clocks: SimulatedClocks, r: np.ndarray, k: np.ndarray, t: np.ndarray,
             rng: RowNoise, stamp: str = "micros") -> Stream:  # fmt: skip
    """The columns every device stream has: bench, sequence number, true time, host receive time (ns) and
    the device's own clock reading under ``stamp``."""
    return {"robot": r, "seq": k, "t_true": t, "host_ns": _host(device.host_link, t, rng),
            stamp: clocks.ticks_at(r, t)}  # fmt: skip


def servo_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float, rate_hz: float,
                 noise: BenchNoise) -> Stream:  # fmt: skip
    """Sync Reads of every position-controlled joint polled at ``rate_hz``: counts as the XM430 reports."""
    joints = [i for i, j in enumerate(robot.joints) if j.drive != "stepper"]
    batch = trace.q.shape[0]
    r, k, t = host_poll_instants(batch, 1.0 / rate_hz, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    counts = servo_counts(
        robot, trace.q[r, idx][:, joints], trace.qd[r, idx][:, joints], trace.torque[r, idx][:, joints], rng
    )
    device = robot.devices[device_of(robot, "joints")]
    return {
        **_stamped(device, clocks, r, k, t, rng, "tick"),
        **counts,
    }


@functools.cache
def drive_scales(eds: str) -> tuple[float, float]:
    """(encoder counts per rad, rated torque N·m) of the CiA 402 drives whose EDS is ``eds`` (its defaults of
    0x2000 and 0x6076: what the driver reads by SDO)."""
    od = canopen.import_od(eds)
    return od[0x2000].default / (2 * np.pi), od[0x6076].default * 1e-3


def drive_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float, rate_hz: float,
                 noise: BenchNoise) -> Stream:  # fmt: skip
    """The CiA 402 drives' answers to the host's SYNC at ``rate_hz``: position and velocity in encoder
    counts, torque in thousandths of the rated torque (what their PDOs carry), operation enabled."""
    joints = [i for i, j in enumerate(robot.joints) if j.drive != "stepper"]
    r, k, t = host_poll_instants(trace.q.shape[0], 1.0 / rate_hz, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    counts_per_rad, rated_nm = drive_scales(str(CAN_DIR / "popup_drive.eds"))
    return {
        **_stamped(robot.devices[device_of(robot, "joints")], clocks, r, k, t, rng),
        "position_counts": np.rint(trace.q[r, idx][:, joints] * counts_per_rad),
        "velocity_counts": np.rint(trace.qd[r, idx][:, joints] * counts_per_rad),
        "torque_per_mille": np.clip(
            np.rint(trace.torque[r, idx][:, joints] / rated_nm * 1000), -32768, 32767
        ),
        "counts_per_rad": np.full(len(r), counts_per_rad),
        "rated_nm": np.full(len(r), rated_nm),
    }


def link_board_stream(robot: RobotDescription, board: str, clocks: SimulatedClocks, trace: Trace, dt: float,
                      noise: BenchNoise) -> Stream:  # fmt: skip
    """A POPUP link board on its own clock at its rate: the orientation of its link's end (roll, pitch, yaw
    at the IMU's resolution) and its four flex sensors' counts."""
    dev = robot.devices[board]
    frame, bend = robot.link_end(dev.link)
    lsb = popup_boards.scale(popup_boards.link_message(dev.ids["board"], popup_boards.ORIENTATION), "Roll")
    r, k, t = device_sample_instants(clocks, 1.0 / dev.rate_hz, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    rotation = robot.chain().frames(trace.q[r, idx], trace.delta[r, idx])[:, frame, :3, :3]
    return {
        **_stamped(dev, clocks, r, k, t, rng),
        "rpy": np.rint(sensors.rpy_from_rotation(rotation) / lsb) * lsb,
        "flex": sensors.flex_counts(trace.delta[r, idx][:, bend], robot.sensors.flex, rng),
    }


def servo_counts(robot: RobotDescription, q: np.ndarray, qd: np.ndarray, torque: np.ndarray,
                 rng: np.random.Generator) -> Stream:  # fmt: skip
    """Present position/velocity/current registers of servos at true angle, speed and drive torque:
    current = torque / K_t + idle · sign(torque) + friction · sign(speed) (smoothed) + noise."""
    servo, noise = robot.servo, robot.sensors.servo
    amps = servo_current_a(servo, torque, qd)
    return {
        "position": sensors.encoder_counts(q, servo.zero_count),
        "velocity": sensors.velocity_counts(qd, rng, noise.velocity_noise_counts),
        "current": sensors.current_counts(amps, noise.current_noise_counts, rng),
    }


def pressure_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float,
                    noise: BenchNoise) -> Stream:  # fmt: skip
    """ADS1115 conversions of every channel, on the board's own (drifting) clock."""
    rate = robot.sensors.pressure.sample_rate_hz
    r, k, t = device_sample_instants(clocks, 1.0 / rate, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    device = robot.devices[device_of(robot, "pressure")]
    return {
        **_stamped(device, clocks, r, k, t, rng),
        "counts": sensors.pressure_to_adc_counts(trace.pressure[r, idx], pressure_spec(robot), rng),
    }


def pressure_spec(robot: RobotDescription) -> PressureSensorSpec:
    """The configured transducer + ADC chain (the robot description's calibration)."""
    return robot.sensors.pressure


def stepper_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float,
                   noise: BenchNoise) -> Stream:  # fmt: skip
    """The Nano's position reports (microsteps of each stepper joint) on its own clock."""
    joints = [i for i, j in enumerate(robot.joints) if j.drive == "stepper"]
    r, k, t = device_sample_instants(clocks, 1.0 / robot.stepper.report_rate_hz, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    steps = np.rint(trace.q[r, idx][:, joints] / robot.stepper.rad_per_microstep).astype(np.int64)
    return {
        **_stamped(robot.devices[device_of(robot, "stepper")], clocks, r, k, t, rng),
        "position_steps": steps,
    }


def tracker_spec(robot: RobotDescription) -> sensors.TrackerSpec:
    """The sensor model's view of the configured tracker."""
    tr = robot.sensors.tracker
    transform = sensors.make_transform(
        sensors.rotation_from_rpy(*tr.base_to_tracker_rpy_rad), np.asarray(tr.base_to_tracker_translation_m)
    )
    return sensors.TrackerSpec(
        base_to_tracker=transform, noise_m=tr.noise_m, field_min_m=np.asarray(tr.field_min_m),
        field_max_m=np.asarray(tr.field_max_m), rms_error_mm_mean=tr.rms_error_mm,
        distortion=robot.effects.tracker_distortion,
    )  # fmt: skip


def tracker_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float,
                   noise: BenchNoise) -> Stream:  # fmt: skip
    """Aurora-like frames at the tracker's own frame rate: pose of the tip coil in the tracker's frame."""
    period = 1.0 / robot.sensors.tracker.frame_rate_hz
    r, k, t = device_sample_instants(clocks, period, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    tip_rot = robot.chain().fk(trace.q[r, idx], trace.delta[r, idx])[..., :3, :3]
    reading = sensors.tracker_measurement(trace.tip_pos[r, idx], tip_rot, tracker_spec(robot), rng)
    return {
        "robot": r,
        "frame": k,
        "t_true": t,
        "host_ns": _host(robot.devices[device_of(robot, "tracker")].host_link, t, rng),
        "position": reading.position_m,
        "quaternion": reading.quaternion,
        "rms_error": reading.rms_error,
        "missing": reading.missing,
        "port_status": reading.port_status,
    }


def tip_acceleration(trace: Trace, dt: float, tip_before: np.ndarray | None = None) -> np.ndarray:
    """Tip acceleration (B, n, 3) in the base frame by second differences of the 1 kHz tip trace:
    a_n = (x_n − 2 x_(n−1) + x_(n−2)) / dt², the acceleration one step earlier (a one-sample delay, like a
    sensor's filter). ``tip_before`` (B, 2, 3) are the two positions before the trace; without them the
    trace is extended linearly (zero acceleration at its first steps)."""
    x = trace.tip_pos
    if tip_before is None:
        first, second = x[:, :1], x[:, 1:2] if x.shape[1] > 1 else x[:, :1]
        tip_before = np.concatenate([3 * first - 2 * second, 2 * first - second], axis=1)
    x = np.concatenate([tip_before, x], axis=1)
    return (x[:, 2:] - 2.0 * x[:, 1:-1] + x[:, :-2]) / dt**2


def accelerometer_stream(robot: RobotDescription, clocks: SimulatedClocks, trace: Trace, dt: float,
                         noise: BenchNoise, tip_before: np.ndarray | None = None,
                         ) -> Stream:  # fmt: skip
    """The tip accelerometer on its own clock: specific force R_tipᵀ (a − g) in the sensor (tip) frame,
    gravity included (at rest it reads +|g| along the sensor's up direction), noisy and quantised."""
    spec = robot.sensors.accelerometer
    r, k, t = device_sample_instants(clocks, 1.0 / spec.sample_rate_hz, trace.t[0] - dt, trace.t[-1])
    idx, rng = _step_index(trace, t, dt), noise.rows(r)
    accel = tip_acceleration(trace, dt, tip_before)[r, idx]
    rot = robot.chain().fk(trace.q[r, idx], trace.delta[r, idx])[..., :3, :3]
    force = np.einsum("nji,nj->ni", rot, accel - np.asarray(robot.gravity_m_s2))
    return {
        **_stamped(robot.devices[spec.device], clocks, r, k, t, rng),
        "acceleration": sensors.accelerometer_reading(
            force, spec.lsb_m_s2, spec.full_scale_m_s2, spec.noise_rms_m_s2, rng
        ),
    }
