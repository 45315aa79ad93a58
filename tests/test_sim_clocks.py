"""Device clocks and host links of the twin."""

import numpy as np
import pytest

from twin.clocks import HostLinkSpec, SimulatedClocks, SimulatedClockSpec, host_receive_ns, unwrap_ticks

TICK = SimulatedClockSpec(
    tick_s=1e-3, wrap=32768, drift_ppm_sigma=40.0, offset_max_s=30.0
)  # Dynamixel Realtime Tick
MICROS = SimulatedClockSpec(tick_s=1e-6, wrap=2**32, drift_ppm_sigma=2000.0, offset_max_s=0.0)  # Uno micros()


def test_same_seed_same_clocks_and_drift_spread():
    a = SimulatedClocks(MICROS, 2000, np.random.default_rng(1))
    b = SimulatedClocks(MICROS, 2000, np.random.default_rng(1))
    np.testing.assert_array_equal(a.drift_ppm, b.drift_ppm)
    np.testing.assert_array_equal(a.offset_s, b.offset_s)
    assert a.batch == 2000
    assert a.drift_ppm.std() == pytest.approx(2000.0, rel=0.1)
    assert abs(a.drift_ppm.mean()) < 4 * 2000.0 / np.sqrt(2000)


def test_offsets_are_drawn_in_range():
    clocks = SimulatedClocks(TICK, 2000, np.random.default_rng(2))
    assert clocks.offset_s.min() >= 0.0 and clocks.offset_s.max() < 30.0
    assert clocks.offset_s.mean() == pytest.approx(15.0, rel=0.05)


def test_device_seconds_broadcast_over_the_batch():
    clocks = SimulatedClocks.from_truth(TICK, np.array([0.0, 100.0, -50.0]), np.array([1.0, 2.0, 3.0]))
    t = np.tile(np.linspace(0.0, 10.0, 5), (3, 1))
    expected = (1 + clocks.drift_ppm[:, None] * 1e-6) * t + clocks.offset_s[:, None]
    np.testing.assert_allclose(clocks.device_seconds(t), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(clocks.device_seconds(t[:, 2]), expected[:, 2], rtol=0, atol=1e-12)
    assert clocks.ticks(t).dtype == np.int64 and clocks.ticks(t).shape == (3, 5)


def test_ticks_run_at_the_drifted_rate():
    clocks = SimulatedClocks.from_truth(MICROS, np.array([1500.0, -800.0]), np.array([2.0, 0.5]))
    t = np.array([[0.0, 1.0], [0.0, 1.0]])
    ticks = clocks.ticks(t)
    np.testing.assert_allclose(ticks[:, 1] - ticks[:, 0], 1e6 * (1 + clocks.drift_ppm * 1e-6), atol=1)
    np.testing.assert_array_equal(clocks.ticks_at(np.array([0, 0, 1, 1]), t.ravel()), ticks.ravel())


def test_realtime_tick_wraps_and_unwraps_exactly():
    clocks = SimulatedClocks.from_truth(TICK, np.array([30.0]), np.array([12.0]))
    t = np.arange(0.0, 120.0, 0.01)[None, :]  # several wraps of 32.768 s
    ticks = clocks.ticks(t)[0]
    assert ticks.min() >= 0 and ticks.max() < 32768 and np.sum(np.diff(ticks) < 0) >= 3
    truth = np.floor(clocks.device_seconds(t)[0] / 1e-3 + 1e-9).astype(np.int64)
    unwrapped = unwrap_ticks(ticks, 32768)
    assert np.all(np.diff(unwrapped) > 0)
    np.testing.assert_array_equal(unwrapped - unwrapped[0], truth - truth[0])


def test_micros_wraps_at_two_to_the_32():
    spec = SimulatedClockSpec(tick_s=1e-6, wrap=2**32, drift_ppm_sigma=0.0, offset_max_s=0.0)
    clocks = SimulatedClocks.from_truth(spec, np.zeros(1), np.array([2**32 * 1e-6 - 0.5]))
    ticks = clocks.ticks(np.array([[0.0, 1.0]]))[0]
    assert ticks[1] < ticks[0]
    assert unwrap_ticks(ticks, 2**32)[1] - ticks[0] == 1_000_000


def test_micros_unwraps_over_several_wraps():
    clocks = SimulatedClocks.from_truth(MICROS, np.array([-2021.0]), np.array([4000.0]))
    t = np.arange(0.0, 20_000.0, 997.0)[None, :]  # gaps < half a wrap (2147 s), ~4.7 wraps
    ticks = clocks.ticks(t)[0]
    assert ticks.max() < 2**32 and np.sum(np.diff(ticks) < 0) >= 4
    truth = np.floor(clocks.device_seconds(t)[0] / 1e-6 + 1e-9).astype(np.int64)
    np.testing.assert_array_equal(unwrap_ticks(ticks, 2**32), truth)  # ticks[0] had not wrapped yet


def test_unwrap_ticks_edge_cases():
    assert unwrap_ticks(np.array([], dtype=np.int64), 10).size == 0
    np.testing.assert_array_equal(unwrap_ticks([7], 10), [7])
    np.testing.assert_array_equal(unwrap_ticks([8, 9, 1, 4, 8, 2], 10), [8, 9, 11, 14, 18, 22])
    with pytest.raises(ValueError, match="1-D"):
        unwrap_ticks(np.zeros((2, 2)), 10)


def test_specs_and_pinned_clocks_are_validated():
    with pytest.raises(ValueError, match="tick_s"):
        SimulatedClockSpec(tick_s=0.0, wrap=None, drift_ppm_sigma=0.0, offset_max_s=0.0)
    with pytest.raises(ValueError, match="must both be"):
        SimulatedClocks.from_truth(TICK, np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="one-sided"):
        HostLinkSpec(latency_s=-0.001, jitter_s=0.001)


@pytest.mark.parametrize("kind", ["uniform", "exponential"])
def test_host_receive_is_one_sided(kind):
    t = np.linspace(0, 10, 20000)
    spec = HostLinkSpec(latency_s=0.001, jitter_s=0.004, kind=kind)
    host = host_receive_ns(t, spec, np.random.default_rng(0))
    delay = host * 1e-9 - t
    assert delay.min() >= 0.001 - 1e-9
    expected_mean = 0.001 + (0.002 if kind == "uniform" else 0.004)
    assert delay.mean() == pytest.approx(expected_mean, rel=0.05)
    assert host.dtype == np.int64


def test_ftdi_16ms_timer_and_zero_jitter():
    t = np.zeros((4, 5000))
    host = host_receive_ns(t, HostLinkSpec(0.001, 0.016, "uniform"), np.random.default_rng(5))
    assert host.shape == t.shape and host.min() >= 1_000_000 and host.max() <= 17_000_000
    assert host.mean() * 1e-9 == pytest.approx(0.009, rel=0.02)
    exact = host_receive_ns(np.array([1.5]), HostLinkSpec(0.002, 0.0), np.random.default_rng(5))
    assert exact[0] == 1_502_000_000


def test_unknown_jitter_kind_is_an_error():
    with pytest.raises(ValueError, match="jitter kind"):
        host_receive_ns(np.zeros(3), HostLinkSpec(0.0, 0.001, "gaussian"), np.random.default_rng(0))
