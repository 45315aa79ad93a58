"""Device clocks and host links of the twin."""

import numpy as np
import pytest

from acquisition.sim.clocks import ClockSpec, DeviceClocks, HostLinkSpec, host_receive_ns, unwrap_ticks

TICK = ClockSpec(tick_s=1e-3, wrap=32768, drift_ppm_sigma=40.0, offset_max_s=30.0)  # Dynamixel Realtime Tick
MICROS = ClockSpec(tick_s=1e-6, wrap=2**32, drift_ppm_sigma=2000.0, offset_max_s=0.0)  # Uno micros()


def test_same_seed_same_clocks_and_drift_spread():
    a = DeviceClocks(MICROS, 2000, np.random.default_rng(1))
    b = DeviceClocks(MICROS, 2000, np.random.default_rng(1))
    np.testing.assert_array_equal(a.drift_ppm, b.drift_ppm)
    assert a.drift_ppm.std() == pytest.approx(2000.0, rel=0.1)


def test_ticks_run_at_the_drifted_rate():
    clocks = DeviceClocks.from_truth(MICROS, np.array([1500.0]), np.array([2.0]))
    t = np.array([[0.0, 1.0]])
    ticks = clocks.ticks(t)
    assert ticks[0, 1] - ticks[0, 0] == pytest.approx(1e6 * (1 + 1500e-6), abs=1)
    np.testing.assert_array_equal(clocks.ticks_at(np.array([0, 0]), t[0]), ticks[0])


def test_realtime_tick_wraps_and_unwraps_exactly():
    clocks = DeviceClocks.from_truth(TICK, np.array([30.0]), np.array([12.0]))
    t = np.arange(0.0, 120.0, 0.01)[None, :]  # several wraps of 32.768 s
    ticks = clocks.ticks(t)[0]
    assert ticks.max() < 32768 and np.sum(np.diff(ticks) < 0) >= 3
    truth = np.floor(clocks.device_seconds(t)[0] / 1e-3 + 1e-9).astype(np.int64)
    np.testing.assert_array_equal(
        unwrap_ticks(ticks, 32768) - unwrap_ticks(ticks, 32768)[0], truth - truth[0]
    )


def test_micros_wraps_at_two_to_the_32():
    spec = ClockSpec(tick_s=1e-6, wrap=2**32, drift_ppm_sigma=0.0, offset_max_s=0.0)
    clocks = DeviceClocks.from_truth(spec, np.zeros(1), np.array([2**32 * 1e-6 - 0.5]))
    ticks = clocks.ticks(np.array([[0.0, 1.0]]))[0]
    assert ticks[1] < ticks[0]
    assert unwrap_ticks(ticks, 2**32)[1] - ticks[0] == 1_000_000


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


def test_unknown_jitter_kind_is_an_error():
    with pytest.raises(ValueError, match="jitter kind"):
        host_receive_ns(np.zeros(3), HostLinkSpec(0.0, 0.001, "gaussian"), np.random.default_rng(0))
