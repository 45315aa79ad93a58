"""Sensor models: Dynamixel counts, pressure chain, tracker readings, rotations."""

import numpy as np
import pytest

from models.robot import PressureSensorSpec
from twin import sensors


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform random rotations (from normalised Gaussian quaternions), independent of the code under test."""
    q = rng.normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def test_encoder_round_trip_within_half_a_count():
    angle = np.random.default_rng(0).uniform(-3, 3, 1000)
    counts = sensors.encoder_counts(angle)
    assert counts.dtype == np.int64
    back = sensors.encoder_angle(counts)
    assert np.abs(back - angle).max() <= np.pi / 4096 + 1e-15  # 0.044°


def test_encoder_zero_and_raw_counts():
    assert sensors.encoder_counts(0.0) == 2048
    assert sensors.encoder_counts(2 * np.pi, zero_count=100) == 4196  # not wrapped into 0…4095
    assert sensors.encoder_angle(1024, zero_count=0) == pytest.approx(np.pi / 2)


def test_current_noise_and_scale():
    counts = sensors.current_counts(np.full(20000, 0.269), 7.0, np.random.default_rng(1))
    assert counts.dtype == np.int64
    assert counts.mean() == pytest.approx(100, abs=0.2)
    assert counts.std() == pytest.approx(7.0, rel=0.05)
    assert sensors.current_counts(np.array([10.0]), 0.0, np.random.default_rng(1))[0] == 1193
    assert sensors.current_counts(np.array([-10.0]), 0.0, np.random.default_rng(1))[0] == -1193


def test_velocity_counts_scale_and_noise():
    rpm = 2 * np.pi / 60
    np.testing.assert_array_equal(sensors.velocity_counts(np.array([0.229, -2.29]) * rpm), [1, -10])
    noisy = sensors.velocity_counts(np.full(20000, 0.0), np.random.default_rng(6), noise_counts_sigma=3.0)
    assert noisy.std() == pytest.approx(3.0, rel=0.05)


def test_signed_conversion_of_sdk_reads():
    np.testing.assert_array_equal(sensors.to_signed(np.array([0xFFFF, 5]), 2), [-1, 5])
    assert sensors.to_signed(0xFFFFFFFF, 4) == -1
    assert sensors.to_signed(0x80, 1) == -128 and sensors.to_signed(0x7FFFFFFF, 4) == 2**31 - 1
    with pytest.raises(ValueError, match="unsigned"):
        sensors.to_signed(0x10000, 2)


def test_pressure_chain_round_trip():
    spec = PressureSensorSpec(
        full_scale_pa=4e5, v_min=0.5, v_max=4.5, adc_lsb_v=125e-6, adc_noise_v=30e-6, sample_rate_hz=250
    )
    p = np.linspace(0, 2.5e5, 5000)
    counts = sensors.pressure_to_adc_counts(p, spec, np.random.default_rng(2))
    assert counts.dtype == np.int64
    back = spec.counts_to_pa(counts)
    pa_per_volt = 4e5 / 4.0
    assert np.abs(back - p).max() < (0.5 * 125e-6 + 5 * 30e-6) * pa_per_volt
    assert np.std(back - p) == pytest.approx(np.hypot(30e-6, 125e-6 / np.sqrt(12)) * pa_per_volt, rel=0.1)


def test_pressure_clips_to_transducer_and_adc_ranges():
    spec = PressureSensorSpec(
        full_scale_pa=4e5, v_min=0.5, v_max=4.5, adc_lsb_v=125e-6, adc_noise_v=0.0, sample_rate_hz=250
    )
    counts = sensors.pressure_to_adc_counts(np.array([-1e5, 0.0, 3.9e5, 1e6]), spec, np.random.default_rng(0))
    np.testing.assert_array_equal(counts, [4000, 4000, 32767, 32767])  # 4.5 V is beyond the ±4.096 V range


def test_quaternion_round_trip():
    rng = np.random.default_rng(3)
    rots = np.concatenate(
        [
            np.stack([sensors.rotation_from_rpy(*a) for a in rng.uniform(-3, 3, (500, 3))]),
            _random_rotations(rng, 500),
        ]
    )
    q = sensors.rotation_to_quaternion(rots)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(sensors.quaternion_to_rotation(q), rots, atol=1e-12)


def test_quaternion_of_half_turns_and_identity():
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 1]], dtype=float)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    half_turns = 2 * axes[:, :, None] * axes[:, None, :] - np.eye(3)  # R = 2 n nᵀ − I
    q = sensors.rotation_to_quaternion(half_turns)
    np.testing.assert_allclose(q[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(q[:, 1:] @ axes.T).diagonal(), 1.0, atol=1e-12)
    np.testing.assert_allclose(sensors.quaternion_to_rotation(q), half_turns, atol=1e-12)
    np.testing.assert_allclose(sensors.rotation_to_quaternion(np.eye(3)), [1, 0, 0, 0], atol=1e-15)


def test_rotation_helpers_are_vectorised():
    rng = np.random.default_rng(7)
    angles = rng.uniform(-3, 3, (4, 3))
    batched = sensors.rotation_from_rpy(angles[:, 0], angles[:, 1], angles[:, 2])
    assert batched.shape == (4, 3, 3)
    np.testing.assert_allclose(batched[2], sensors.rotation_from_rpy(*angles[2]), atol=0)
    np.testing.assert_allclose(batched @ np.swapaxes(batched, -1, -2), np.broadcast_to(np.eye(3), (4, 3, 3)),
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(sensors.rotation_from_rpy(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    transform = sensors.make_transform(batched, rng.normal(size=(4, 3)))
    assert transform.shape == (4, 4, 4)
    np.testing.assert_array_equal(transform[:, 3], np.broadcast_to([0, 0, 0, 1.0], (4, 4)))


def _spec():
    transform = sensors.make_transform(
        sensors.rotation_from_rpy(0.2, -0.1, 1.3), np.array([0.01, -0.02, 0.3])
    )
    return sensors.TrackerSpec(transform, 0.25e-3, np.full(3, -0.25), np.array([0.25, 0.25, 0.75]), 0.3)


def test_tracker_reading_inside_and_outside_the_volume():
    spec = _spec()
    rng = np.random.default_rng(4)
    inside = np.zeros((20000, 3))
    r = sensors.tracker_measurement(inside, np.broadcast_to(np.eye(3), (20000, 3, 3)), spec, rng)
    expected = spec.base_to_tracker[:3, 3]
    assert not r.missing.any()
    np.testing.assert_allclose(r.position_m.mean(axis=0), expected, atol=2e-5)
    np.testing.assert_allclose(r.position_m.std(axis=0), 0.25e-3, rtol=0.05)
    np.testing.assert_allclose(sensors.quaternion_to_rotation(r.quaternion[0]), spec.base_to_tracker[:3, :3],
                               atol=1e-12)  # fmt: skip
    far = sensors.tracker_measurement(np.array([[5.0, 0, 0]]), np.eye(3)[None], spec, rng)
    assert far.missing[0] and np.isnan(far.position_m).all() and np.isnan(far.quaternion).all()
    assert np.isnan(far.rms_error[0])
    assert far.port_status[0] & sensors.PORT_OUT_OF_VOLUME
    assert far.port_status[0] == 0x71


def test_tracker_pose_of_batched_points_in_the_tracker_frame():
    spec = _spec()
    rng = np.random.default_rng(8)
    rot, trans = spec.base_to_tracker[:3, :3], spec.base_to_tracker[:3, 3]
    # points drawn inside the box in tracker coordinates, mapped back to the base frame: (B, N, 3)
    p_tracker = rng.uniform(spec.field_min_m + 0.01, spec.field_max_m - 0.01, size=(8, 50, 3))
    p_base = (p_tracker - trans) @ rot
    tip_rot = _random_rotations(rng, 400).reshape(8, 50, 3, 3)
    r = sensors.tracker_measurement(p_base, tip_rot, spec, rng)
    assert r.position_m.shape == (8, 50, 3) and r.quaternion.shape == (8, 50, 4)
    assert r.missing.shape == r.rms_error.shape == r.port_status.shape == (8, 50)
    assert not r.missing.any() and np.all(r.port_status == 0x31)
    assert np.all(np.abs(r.position_m - p_tracker) < 5 * spec.noise_m)
    np.testing.assert_allclose(np.linalg.norm(r.quaternion, axis=-1), 1.0, atol=1e-12)
    assert np.all(r.quaternion[..., 0] >= 0)
    np.testing.assert_allclose(sensors.quaternion_to_rotation(r.quaternion), rot @ tip_rot, atol=1e-12)
    assert np.all(np.isfinite(r.rms_error) & (r.rms_error > 0))
    assert r.rms_error.mean() == pytest.approx(0.3, rel=0.05)


def test_tracker_is_deterministic_per_seed_and_validates_its_spec():
    spec = _spec()
    a = sensors.tracker_measurement(np.zeros((3, 3)), np.eye(3), spec, np.random.default_rng(9))
    b = sensors.tracker_measurement(np.zeros((3, 3)), np.eye(3), spec, np.random.default_rng(9))
    np.testing.assert_array_equal(a.position_m, b.position_m)
    with pytest.raises(ValueError, match="field_min_m"):
        sensors.TrackerSpec(np.eye(4), 0.25e-3, np.full(3, 0.5), np.full(3, 0.25), 0.3)
