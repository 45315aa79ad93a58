"""The POPUP twin's tip accelerometer and hammer tap: gravity at rest, sample rate, and the free oscillation
after a tap at Table 1's damped frequency with the configured damping (seed 001)."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.plans.popup_experiments import bench_robot
from models.robot import load_robot
from twin.world import World

SEED = 5
HORIZONTAL = np.radians([0.0, 90.0, 90.0])  # link 1 vertical, link 2 horizontal
TABLE1_INERTIA_KGM2 = 0.0358  # twin.md: I = k̂ / (2π f_s)² at every pressure
PRESSURES_PA = np.array([10e3, 50e3, 90e3])


@pytest.fixture(scope="module")
def link_bench():
    """The paper's link bench: no end-effector flange, link 1 as a fixed joint."""
    return bench_robot(load_robot("popup"), {"without_masses": ["flange"], "rigid_links": ["link1"]})


def _settled_world(robot, pressures_pa, seconds: float = 4.0) -> World:
    world = World(robot, batch=len(pressures_pa), seed=SEED, q0=HORIZONTAL, pressure_pa=pressures_pa[:, None])
    world.settle(seconds)
    return world


def test_accelerometer_reads_gravity_at_rest_at_1khz(link_bench):
    world = _settled_world(link_bench, PRESSURES_PA)
    s = world.read(world.run_for(2.0))["accelerometer"]
    spec = link_bench.sensors.accelerometer
    noise = spec.noise_density_m_s2_per_sqrt_hz * np.sqrt(spec.bandwidth_hz)
    for r in range(len(PRESSURES_PA)):
        a = s["acceleration"][s["robot"] == r]
        micros = s["micros"][s["robot"] == r]
        rate = 1e6 / np.median(np.diff(micros.astype(np.int64)) % 2**32)
        assert rate >= 500 and rate == pytest.approx(spec.sample_rate_hz, rel=2e-3)
        assert len(a) == pytest.approx(2.0 * spec.sample_rate_hz, abs=3)
        assert np.linalg.norm(a.mean(axis=0)) == pytest.approx(9.81, abs=0.01)
        assert np.all(a.std(axis=0) < 2 * noise) and np.all(a.std(axis=0) > 0.5 * noise)
    assert s["micros"].max() < 2**32


def test_tap_impulse_over_kernel_inertia(link_bench):
    world = _settled_world(link_bench, PRESSURES_PA[:1], seconds=0.5)
    inertia = world.virtual_joint_inertia()[0, -1]
    assert inertia == pytest.approx(TABLE1_INERTIA_KGM2, rel=0.01)
    before = world.state.delta_dot[0, -1]
    world.tap(0.02)
    assert world.state.delta_dot[0, -1] - before == pytest.approx(0.02 / inertia)


def _dominant_frequency_hz(x: np.ndarray, rate_hz: float) -> float:
    """The FFT (zero-padded, rectangular window) peak of a decaying free oscillation."""
    n_fft = 1 << 19
    spectrum = np.abs(np.fft.rfft(x, n_fft))
    return float(np.fft.rfftfreq(n_fft, 1.0 / rate_hz)[np.argmax(spectrum)])


def _log_decrement_damping_ratio(x: np.ndarray, cycles: int = 6) -> float:
    """ζ from the logarithmic decrement of successive positive peaks (fit over ``cycles`` peaks)."""
    inner = x[1:-1]
    peaks = np.flatnonzero((inner > x[:-2]) & (inner >= x[2:]) & (inner > 0.3 * x.max())) + 1
    peaks = peaks[:cycles]
    decrement = -np.polyfit(np.arange(len(peaks)), np.log(x[peaks]), 1)[0]
    return decrement / np.sqrt(4 * np.pi**2 + decrement**2)


def test_tap_rings_at_table1_damped_frequency(link_bench):
    world = _settled_world(link_bench, PRESSURES_PA)
    world.read(world.step(10))  # the accelerometer's differentiator now has the samples before the tap
    world.tap(0.02)
    s = world.read(world.run_for(3.0))["accelerometer"]
    table = link_bench.link_table("link2")
    inertia = world.virtual_joint_inertia()[:, -1]
    rate = link_bench.sensors.accelerometer.sample_rate_hz
    for r, p in enumerate(PRESSURES_PA):
        a = s["acceleration"][s["robot"] == r]
        rest = a[-500:].mean(axis=0)
        axis = int(np.argmax((a[:1000] - rest).std(axis=0)))
        x = (a - rest)[20:1500, axis]  # from 20 ms after the tap (the hammer's spike saturates the sensor)
        k = np.interp(p, table.pressure_pa, table.stiffness_nm_per_rad)
        c = np.interp(p, table.pressure_pa, table.damping_nms_per_rad)
        i = TABLE1_INERTIA_KGM2
        f_d = np.sqrt(k / i - (c / (2 * i)) ** 2) / (2 * np.pi)
        assert _dominant_frequency_hz(x, rate) == pytest.approx(f_d, rel=0.02)
        zeta = c / (2 * np.sqrt(k * inertia[r]))
        assert _log_decrement_damping_ratio(x if x[np.argmax(np.abs(x))] > 0 else -x) == pytest.approx(
            zeta, rel=0.2
        )


def test_the_rigs_link_boards_sense_what_the_simulated_streams_compute():
    """The rig's link boards (the CAN emulators' IMU, read sample by sample as the bus asks) against the
    simulated streams' formula on the same states, in numpy (``DHChain``): the link end's rotation, and the
    tip's specific force Rᵀ (ẍ − g), while the arm moves and after a tap, wherever the ring wraps."""
    from twin.rig import Rig

    popup = load_robot("popup")
    rig = Rig(popup, seed=SEED)
    chain, gravity, dt = popup.chain(), np.asarray(popup.gravity_m_s2), rig.world.dt
    rig.world.commands.goal[0, 0] = 0.6  # the base turns: the tip accelerates
    boards = {name: node.link for name, node in rig.boards.items() if hasattr(node, "link")}
    assert set(boards) == {"link1_board", "link2_board"}
    q, delta, tip, forces, rotations = [], [], [], [], {name: [] for name in boards}
    chunks = np.random.default_rng(SEED).integers(1, 8, 80)  # steps the rig takes between the bus's reads
    k = 2
    for chunk in chunks:
        if k <= 200 < k + chunk:
            rig.world.tap(0.02)
        rig.advance(rig.step_due_s(k + chunk - 1))  # the rig ahead of the boards, as when the host wakes late
        for j in range(k, k + chunk):
            t = rig.step_due_s(j)
            step = rig.recent.at(t)
            q.append(step.q.copy()), delta.append(step.delta.copy()), tip.append(step.tip.copy())
            for name, board in boards.items():
                rotations[name].append(board._rotation(step).copy())
            boards["link2_board"].acceleration(t)  # as the bus samples it
            forces.append(boards["link2_board"]._forces[step.slot].copy())
        k += chunk
    q, delta, tip = np.array(q), np.array(delta), np.array(tip)
    frames = chain.frames(q, delta)
    for name, board in boards.items():
        np.testing.assert_allclose(np.array(rotations[name])[1:], frames[1:, board.frame, :3, :3], atol=1e-12)
    accel = (tip[2:] - 2.0 * tip[1:-1] + tip[:-2]) / dt**2
    expected = np.einsum("nji,nj->ni", frames[2:, boards["link2_board"].frame, :3, :3], accel - gravity)
    assert np.abs(accel).max() > 0.5  # it moved
    np.testing.assert_allclose(np.array(forces)[2:], expected, atol=1e-6)
