"""The digital twin: physics trends, sensor streams, determinism, batch independence."""

import numpy as np
import pytest

from models import prbm
from models.robot import Hysteresis, load_robot
from twin import streams
from twin.survey import encoder_tip_error_mm, experiment1_survey
from twin.world import World

# seed 001, Table 1: p (kPa), f_s (Hz)
TABLE1_F_S = {
    10: 15.04,
    20: 15.63,
    30: 15.94,
    40: 16.17,
    50: 16.44,
    60: 16.56,
    70: 16.65,
    80: 16.83,
    90: 16.93,
}


def _link2_bench(popup):
    """POPUP's link 2 alone as the paper's cantilever test: no flange, no hysteresis (small amplitude)."""
    links = [
        link.model_copy(update={"hysteresis": Hysteresis(delta_h_rad=0.0, tau_y_nm=1.0)})
        for link in popup.links
    ]
    masses = [m for m in popup.masses if m.name != "flange"]
    return popup.model_copy(update={"links": links, "masses": masses})


def _dominant_frequency(signal: np.ndarray, dt: float) -> float:
    """Frequency from the mean period between upward zero crossings (interpolated)."""
    x = signal - signal[len(signal) // 2 :].mean()
    i = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    crossings = (i + x[i] / (x[i] - x[i + 1])) * dt
    return 1.0 / np.diff(crossings).mean()


def test_popup_link2_twin_rings_at_table1_frequencies(popup):
    """Table 1 consistency: the twin's link-2 model, kicked at 10…90 kPa, rings within 1 % of f_s."""
    pressures = np.array(sorted(TABLE1_F_S), dtype=float) * 1e3
    world = World(_link2_bench(popup), batch=len(pressures), seed=1, q0=np.deg2rad([0, 60, -120]),
                  pressure_pa=pressures[:, None])  # fmt: skip
    world.settle(1.0)
    d22 = world.layout.virtual.index("d22")
    world.state.delta_dot[:, d22] = 0.05  # a hammer tap
    trace = world.run_for(1.5)
    for b, p_kpa in enumerate(sorted(TABLE1_F_S)):
        f = _dominant_frequency(trace.delta[b, :, d22], world.dt)
        assert f == pytest.approx(TABLE1_F_S[p_kpa], rel=0.01), f"{p_kpa} kPa: {f:.2f} Hz"


def test_vsl_error_grows_with_payload_and_falls_with_pressure(vsl):
    """Experiment 1's trend on the twin, printed as the grid (mean tip error, mm)."""
    soft = experiment1_survey(vsl, trajectory="curve", seed=3)
    rigid = experiment1_survey(load_robot("vsl_rigid"), trajectory="curve", pressures_bar=(2.0,), seed=3)
    print("\nVSL twin, curve, mean tip error (mm):\n", soft.round(2).to_string())
    print("rigid links:\n", rigid.round(2).to_string())
    values = soft.to_numpy()
    assert np.all(np.diff(values, axis=1) > 0), "error must grow with payload at every pressure"
    assert np.all(np.diff(values, axis=0) < 0), "error must fall with pressure at every payload"
    assert np.all(rigid.to_numpy() < values.min()), "the rigid arm errs less than any VSL cell"
    assert np.all(rigid.to_numpy() > 0.05), "but not zero: printed links bend a little"


def test_vsl_extended_pose_deflection_matches_twin_reference(vsl):
    """twin.md: ≈ 15–20 mm tip error at 0.5 bar / 100 g in an extended pose, ≈ 4–5 mm at 2 bar. (With its
    k ∝ p the two figures imply a ratio of 4, i.e. ≈ 3.75 mm at 2 bar; the lower bound allows for that.)"""
    world = World(vsl, batch=2, q0=np.zeros(3), pressure_pa=np.array([[0.5e5], [2.0e5]]), payload_kg=0.1)
    world.settle(3.0)
    error = encoder_tip_error_mm(vsl, world.step(1))[:, -1]
    assert 13.5 <= error[0] <= 20.0
    assert 2.8 <= error[1] <= 5.5


def _streams(world, seconds):
    read = world.read(world.run_for(seconds))
    assert set(read) == {"servo_bus", "pressure_board", "stepper_board", "tracker"}
    return read["servo_bus"], read["pressure_board"], read["tracker"], read["stepper_board"]


def _scripted(robot, seed, batch=2):
    world = World(robot, batch=batch, seed=seed, q0=np.deg2rad([0, 30, -60]), payload_kg=0.05)
    world.command_joints(np.deg2rad([10, 60, -80]))
    world.command_pressure(1.2e5)
    return _streams(world, 1.0)


def test_same_seed_gives_bit_identical_streams(vsl):
    first, second = _scripted(vsl, seed=7), _scripted(vsl, seed=7)
    for a, b in zip(first, second, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    other = _scripted(vsl, seed=8)
    assert not np.array_equal(first[1]["counts"], other[1]["counts"])


def test_a_robot_in_a_batch_behaves_as_if_alone(vsl):
    """Batch members are independent: the same commands give the same true trace alone or in a batch."""
    payloads = np.array([0.0, 0.1, 0.05])
    batch = World(vsl, batch=3, q0=np.deg2rad([0, 30, -60]), payload_kg=payloads)
    alone = World(vsl, batch=1, q0=np.deg2rad([0, 30, -60]), payload_kg=payloads[1])
    for w in (batch, alone):
        w.command_joints(np.deg2rad([0, 70, -100]))
    tb, ta = batch.run_for(0.5), alone.run_for(0.5)
    np.testing.assert_array_equal(tb.tip_pos[1], ta.tip_pos[0])
    np.testing.assert_array_equal(tb.delta[1], ta.delta[0])


def test_servo_droop_and_current_grow_with_payload(vsl):
    world = World(vsl, batch=2, q0=np.deg2rad([0, 20, -40]), payload_kg=np.array([0.0, 0.1]))
    world.settle(1.0)
    trace = world.step(1)
    goal = world.commands.goal
    droop = np.abs(trace.q[:, -1, 1] - goal[:, 1])
    assert droop[1] > droop[0] > 0.0
    assert abs(trace.torque[1, -1, 1]) > abs(trace.torque[0, -1, 1])
    expected = trace.torque[:, -1, 1] / vsl.servo.stiffness_nm_per_rad
    np.testing.assert_allclose(droop, np.abs(expected), rtol=0.05)


def test_links_ring_after_a_fast_move(vsl):
    world = World(vsl, batch=1, q0=np.deg2rad([0, 20, -40]), pressure_pa=0.5e5)
    world.settle(1.0)
    world.command_joints(np.deg2rad([0, 45, -40]), profile_vel=0.0, profile_acc=0.0)  # unlimited: a jolt
    trace = world.run_for(2.0)
    d2 = trace.delta[0, :, 0]
    settled = d2[-200:].mean()
    tail = d2[100:1000] - settled
    assert np.abs(tail).max() > 5e-4, "the link should ring after a jolt"
    assert np.abs(d2[-200:] - settled).max() < 0.2 * np.abs(tail).max(), "and the ringing decays"


def test_regulator_lags_and_valve_holds_with_slow_leak(vsl):
    world = World(vsl, batch=1, pressure_pa=1.0e5)
    world.command_pressure(1.5e5)
    trace = world.run_for(0.3)
    p = trace.pressure[0, :, 0]
    dead = vsl.pneumatics.regulator_dead_time_s
    assert p[int(dead / world.dt) - 1] == pytest.approx(1.0e5), "nothing moves during the dead time"
    tau = vsl.pneumatics.regulator_time_constant_s
    i63 = int((dead + tau) / world.dt)
    assert p[i63] == pytest.approx(1.0e5 + 0.63 * 0.5e5, rel=0.02)
    world.set_valves(False)
    world.command_pressure(0.0)
    held = world.run_for(60.0).pressure[0, -1, 0]
    expected = p[-1] * np.exp(-60.0 / vsl.pneumatics.leak_time_constant_s)
    assert held == pytest.approx(expected, rel=1e-3), "valve closed: only the slow leak"


def test_tracker_reports_missing_outside_the_field_volume(vsl):
    world = World(vsl, batch=2, q0=np.deg2rad([0, 30, -60]))
    world.command_joints(np.array([np.deg2rad([0, 30, -60]), np.deg2rad([80, 30, -60])]))  # swing J1 far out
    world.run_for(2.0)
    frames = _streams(world, 0.5)[2]
    inside = frames["robot"] == 0
    assert not frames["missing"][inside].any()
    assert frames["missing"][~inside].all()
    assert np.isnan(frames["position"][~inside]).all(), "MISSING is NaN, never a zero pose"
    assert np.all(frames["port_status"][~inside] & 0x40), "out-of-volume bit set"
    period = np.diff(frames["frame"][inside])
    assert np.all(period == 1), "consecutive frame numbers at the tracker's own rate"


def test_tracker_frames_follow_the_true_tip_through_the_configured_transform(vsl):
    world = World(vsl, batch=1, q0=np.deg2rad([0, 30, -60]))
    world.settle(0.5)
    trace = world.run_for(1.0)
    frames = streams.tracker_stream(vsl, world.clocks["tracker"], trace, world.dt, world.noise("tracker"))
    transform = streams.tracker_spec(vsl).base_to_tracker
    tip = trace.tip_pos[0, -1]
    expected = transform[:3, :3] @ tip + transform[:3, 3]
    residual = frames["position"] - expected
    assert (
        np.abs(residual.mean(axis=0)).max() < 3 * vsl.sensors.tracker.noise_m / np.sqrt(len(residual)) + 1e-5
    )
    assert residual.std(axis=0) == pytest.approx([vsl.sensors.tracker.noise_m] * 3, rel=0.4)


def test_device_clocks_drift_and_wrap(vsl):
    world = World(vsl, batch=4, seed=11)
    trace = world.run_for(40.0)
    servo = streams.servo_stream(
        vsl, world.clocks["servo_bus"], trace, world.dt, 50.0, world.noise("servo_bus")
    )
    tick = servo["tick"][servo["robot"] == 0]
    assert tick.max() < 32768 and np.any(np.diff(tick) < 0), "the Realtime Tick wraps at 32767"
    board = world.clocks["pressure_board"]
    assert np.abs(board.drift_ppm).max() > 100, "the Uno's resonator drifts by hundreds of ppm"
    pressure = streams.pressure_stream(vsl, board, trace, world.dt, world.noise("pressure_board"))
    first = pressure["robot"] == 0
    micros = pressure["micros"][first].astype(float)
    t = pressure["t_true"][first]
    slope = np.polyfit(t, np.unwrap(micros * 2 * np.pi / 2**32) * 2**32 / (2 * np.pi), 1)[0]
    assert slope == pytest.approx(1e6 * (1 + board.drift_ppm[0] * 1e-6), rel=2e-6)
    host = pressure["host_ns"][first] * 1e-9
    assert np.all(host >= t), "host receive time is never before the sample"


def test_pressure_stream_reads_back_within_sensor_noise(vsl):
    world = World(vsl, batch=1, pressure_pa=1.5e5)
    trace = world.run_for(1.0)
    s = streams.pressure_stream(
        vsl, world.clocks["pressure_board"], trace, world.dt, world.noise("pressure_board")
    )
    spec = vsl.sensors.pressure
    p = vsl.sensors.pressure.counts_to_pa(s["counts"])
    pa_per_volt = spec.full_scale_pa / (spec.v_max - spec.v_min)
    assert np.abs(p - 1.5e5).max() < 6 * (spec.adc_noise_v + spec.adc_lsb_v) * pa_per_volt
    assert len(p) == pytest.approx(spec.sample_rate_hz, rel=0.02)


def test_prbm_statics_match_the_twin_at_rest(vsl):
    """At rest the twin's link deflection is the prbm statics of its own joint torque: δ = τ/k − δ_h z."""
    world = World(vsl, batch=1, q0=np.deg2rad([0, 10, -20]), pressure_pa=1.0e5, payload_kg=0.075)
    world.settle(3.0)
    st = world.state
    k = prbm.interp_table(1.0e5, vsl.link_table("upper_vsl").pressure_pa,
                          vsl.link_table("upper_vsl").stiffness_nm_per_rad)  # fmt: skip
    expected = prbm.static_deflection(
        st.vj_torque[0, 0], k, vsl.links[0].hysteresis.delta_h_rad, st.hyst_z[0, 0]
    )
    assert st.delta[0, 0] == pytest.approx(expected, rel=1e-3)


def test_unlimited_profile_is_bounded_by_the_drives_limits(vsl):
    """Profile 0 means 'as fast as the motor can': never more than stall torque or top speed (a torque-off
    hold at the drooped position once made the droop model swing the joint by radians)."""
    world = World(vsl, batch=1, q0=np.deg2rad([0, 30, -60]))
    world.command_joints(world.state.out_pos[0], profile_vel=0.0, profile_acc=0.0)
    trace = world.step(300)
    assert np.abs(trace.torque).max() <= vsl.servo.max_torque_nm + 1e-12
    assert np.abs(trace.q[0, :, 1:] - trace.q[0, 0, 1:]).max() < np.deg2rad(2.0)
    world.command_joints(np.deg2rad([0, 90, -60]), profile_vel=0.0, profile_acc=0.0)
    moving = world.run_for(0.5)
    speed = np.abs(moving.qd[0, :, 1])
    # the first-order droop loop overshoots for a few ms when the torque saturates (documented in kernel.py)
    assert speed.max() <= vsl.servo.max_speed_rad_s * 2.0
    assert np.median(speed[speed > 0.1]) <= vsl.servo.max_speed_rad_s * 1.05
    assert np.abs(moving.torque[0, :, 1]).max() <= vsl.servo.max_torque_nm + 1e-12
