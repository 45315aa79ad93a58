"""Sensor models: Dynamixel counts, pressure chain, tracker readings, rotations."""

import numpy as np
import pytest

from acquisition.sim import sensors


def test_encoder_round_trip_within_half_a_count():
    angle = np.random.default_rng(0).uniform(-3, 3, 1000)
    back = sensors.encoder_angle(sensors.encoder_counts(angle))
    assert np.abs(back - angle).max() <= np.pi / 4096 + 1e-15


def test_current_noise_and_scale():
    counts = sensors.current_counts(np.full(20000, 0.269), 7.0, np.random.default_rng(1))
    assert counts.mean() == pytest.approx(100, abs=0.2)
    assert counts.std() == pytest.approx(7.0, rel=0.05)
    assert sensors.current_counts(np.array([10.0]), 0.0, np.random.default_rng(1))[0] == 1193


def test_signed_conversion_of_sdk_reads():
    np.testing.assert_array_equal(sensors.to_signed(np.array([0xFFFF, 5]), 2), [-1, 5])
    assert sensors.to_signed(0xFFFFFFFF, 4) == -1


def test_pressure_chain_round_trip():
    spec = sensors.PressureSensorSpec(4e5, 0.5, 4.5, 125e-6, 30e-6)
    p = np.linspace(0, 2.5e5, 5000)
    back = sensors.adc_counts_to_pressure(
        sensors.pressure_to_adc_counts(p, spec, np.random.default_rng(2)), spec
    )
    pa_per_volt = 4e5 / 4.0
    assert np.abs(back - p).max() < (0.5 * 125e-6 + 5 * 30e-6) * pa_per_volt


def test_quaternion_round_trip():
    rng = np.random.default_rng(3)
    rots = np.stack([sensors.rotation_from_rpy(*a) for a in rng.uniform(-3, 3, (1000, 3))])
    q = sensors.rotation_to_quaternion(rots)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(sensors.quaternion_to_rotation(q), rots, atol=1e-12)


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
    assert far.port_status[0] & sensors.PORT_OUT_OF_VOLUME
