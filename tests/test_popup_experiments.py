"""POPUP protocols (seed 001): plans well formed, and short simulated runs whose sessions carry the tip
accelerometer and the link pressures; the static test's loop; the deployment's pressure checks."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader

from acquisition.plans import experiments
from acquisition.plans import popup_experiments as pp
from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.recorder.sessions import SessionStore
from acquisition.safety import SafetyChecker
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.fast_read import read_fixed_topics
from models import prbm
from twin.runner import SIM_EPOCH_NS, session_id, simulate_experiment

pytestmark = pytest.mark.slow  # module fixtures of seconds each: the whole module is slow-tier

SEED = 3
REDUCED = {
    "popup_static": {"pressures_kpa": [30], "repetitions": 2, "settle_s": 1.5, "hold_s": 0.5},
    "popup_impact": {"pressures_kpa": [20, 80], "taps": 3, "record_s": 2.0, "settle_s": 2.0},
    "popup_deploy": {},
    "popup_reach": {},
}


def _plans(name: str, popup, **overrides) -> tuple[dict, list[Plan]]:
    params = experiments.load_experiment(name, **overrides)
    return params, pp.EXPERIMENTS[name](pp.bench_robot(popup, params), params)


def _kinds(plan: Plan, kind: EventKind, label: str | None = None) -> list[tuple[float, Event]]:
    return [(t, e) for t, e in plan.events if e.kind == kind and (label is None or e.label == label)]


def test_static_plans(popup):
    params, plans = _plans("popup_static", popup)
    assert [p.name for p in plans] == [f"popup_static/{k}kPa" for k in (10, 20, 30, 40, 50)]
    n_loads = params["load_steps"] + 1
    arm, own = 0.590, 0.30 * 9.81 * 0.295  # link 2's hinge (D-H row d22) to tip; its own moment there
    for p, kpa in zip(plans, params["pressures_kpa"], strict=True):
        assert len(_kinds(p, EventKind.REPETITION_START)) == len(_kinds(p, EventKind.REPETITION_END)) == 3
        settled = _kinds(p, EventKind.SETTLED)
        assert [e.index for _, e in settled] == list(range(3 * (2 * n_loads - 1)))
        # the heaviest mass bends link 2 to 0.8 M_c(p), M_c = (π²/4) p r³, in equal steps from 0
        top = (0.8 * np.pi**2 / 4 * kpa * 1e3 * 0.055**3 - own) / (9.81 * arm)
        loads = np.asarray(p.parameters["loads_kg"])
        np.testing.assert_allclose(loads, np.linspace(0, top, n_loads), atol=0.6e-3)
        assert p.payload_kg.max() == loads.max()
        assert np.allclose(p.goal_q, np.radians(params["pose_deg"])) and len(p.tap_t) == 0


def test_impact_plans(popup):
    params, plans = _plans("popup_impact", popup)
    assert len(plans) == 9
    for p in plans:
        taps = _kinds(p, EventKind.PLAN_STEP, "tap")
        assert len(p.tap_t) == len(taps) == params["taps"] >= 3
        assert np.allclose(p.tap_t, [t for t, _ in taps]) and np.all(p.tap_impulse_nms > 0)
        assert p.tap_t[0] >= params["settle_s"] and p.duration_s >= p.tap_t[-1] + params["record_s"]


def test_deploy_plan_inflates_link1_then_link2(popup):
    _, (plan,) = _plans("popup_deploy", popup)
    start = plan.at(np.array([0.0]))
    assert np.all(start["pressure_pa"] == 0) and not start["valve_open"].any()
    checks = pp.pressure_checks(plan.events)
    assert [(ch, v) for _, ch, v in checks] == [(0, 50e3), (1, 50e3)]
    ((t_inflate2, _),) = [(t, e) for t, e in _kinds(plan, EventKind.PLAN_STEP, "inflate") if e.index == 1]
    assert t_inflate2 >= checks[0][0]
    assert plan.at(np.array([checks[0][0] - 1e-3]))["pressure_pa"][0, 1] == 0


def test_reach_plan_follows_the_velocity_law_to_the_target(popup):
    params, (plan,) = _plans("popup_reach", popup)
    assert plan.name == "popup_reach/60kPa-2000g" and plan.parameters["allow_wrinkling"]
    target = np.asarray(params["target_mm"]) * 1e-3
    np.testing.assert_allclose(plan.goal_q[0], np.radians(params["q0_deg"]))
    assert np.linalg.norm(popup.chain().position(plan.goal_q[-1]) - target) < params["tolerance_mm"] * 1e-3
    step = np.diff(plan.goal_t[1:-1])  # the path (then the target again, at the drives' own speed)
    np.testing.assert_allclose(step, params["dt_s"], atol=1e-9)  # one set-point per SYNC period
    settled = _kinds(plan, EventKind.SETTLED)
    assert [e.index for _, e in settled] == [-1, 0, 1] and [e.value for _, e in settled][1:] == [2.0, 2.0]
    ((t_hang, hung),) = [(t, e) for t, e in _kinds(plan, EventKind.PAYLOAD) if e.value > 0]
    assert hung.value == 2.0 and t_hang < settled[1][0] < _kinds(plan, EventKind.REPETITION_START)[0][0]
    assert SafetyChecker(popup).check_plan(plan) == []  # past M_w, held below collapse


def test_survey_plan_spreads_safe_settled_poses_over_the_joint_box(popup):
    params, (plan,) = _plans("popup_survey", popup)
    settled = _kinds(plan, EventKind.SETTLED)
    assert [e.index for _, e in settled] == list(range(params["points"]))
    assert {e.value for _, e in settled} == {params["hold_s"]}
    lo, hi = (np.radians(params["joints_deg"][k]) for k in ("min", "max"))
    assert ((plan.goal_q >= lo) & (plan.goal_q <= hi)).all()
    assert np.ptp(plan.goal_q, axis=0).min() > 0.5 * (hi - lo).min()  # spread, not bunched
    assert ((plan.pressure_pa >= 40e3) & (plan.pressure_pa <= 90e3)).all()
    assert SafetyChecker(popup).check_plan(plan) == []
    tip = popup.chain().position(plan.goal_q)
    assert np.linalg.svd(tip - tip.mean(axis=0), compute_uv=False).min() > 0.1  # a volume: it registers
    with pytest.raises(experiments.ExperimentError, match="joints_deg's min below its max on every axis"):
        experiments.expand_experiment("popup_survey", {"joints_deg": {"min": [0, 0, 0], "max": [0, 1, 1]}})


def test_plan_taps_must_be_ordered_and_inside():
    b = PlanBuilder("t", "popup", 3, 2).goto(np.zeros(3)).pressure(1e4).payload(0.0).wait(1.0).tap(0.01)
    plan = b.wait(1.0).build()
    assert plan.tap_t.tolist() == [1.0] and plan.tap_impulse_nms.tolist() == [0.01]
    with pytest.raises(ValueError, match="tap times"):
        Plan(**{**plan.__dict__, "tap_t": np.array([3.0])})


@pytest.fixture(scope="module")
def sessions(tmp_path_factory, popup):
    directory = tmp_path_factory.mktemp("popup")
    out = {}
    for name, overrides in REDUCED.items():
        _, plans = _plans(name, popup, **overrides)
        simulate_experiment(name, SessionStore(directory), seed=SEED, overrides=overrides)
        out[name] = []
        for plan in plans:
            (part,) = sorted((directory / session_id(plan)).glob("*.mcap"))
            with open(part, "rb") as f:
                events = [
                    ((m.log_time - SIM_EPOCH_NS) / 1e9, Event.decode(m.data))
                    for _, _, m in make_reader(f).iter_messages(topics=[T.EVENTS], log_time_order=True)
                ]
            out[name].append((plan, read_fixed_topics(part), events))
    return out


def _seconds(log_time: np.ndarray) -> np.ndarray:
    return (log_time.astype(np.int64) - SIM_EPOCH_NS) / 1e9


@pytest.mark.parametrize("name", list(REDUCED))
def test_sessions_have_accelerometer_and_pressures(sessions, popup, name):
    for plan, data, _ in sessions[name]:
        accel, pressure = data[T.ACCEL], data[T.PRESSURE]
        accel_hz, pressure_hz = len(accel) / plan.duration_s, len(pressure) / plan.duration_s
        assert accel_hz == pytest.approx(popup.sensors.accelerometer.sample_rate_hz, rel=0.02)
        assert pressure_hz == pytest.approx(popup.sensors.pressure.sample_rate_hz, rel=0.02)
        assert accel.rows["acceleration"].shape == (len(accel), 3)
        settled = [t for t, e in plan.events if e.kind == EventKind.SETTLED]  # at rest before it
        before = np.searchsorted(_seconds(accel.log_time), settled[0]) if settled else 200
        rest = accel.rows["acceleration"][before - 200 : before].mean(axis=0)
        assert np.linalg.norm(rest) == pytest.approx(9.81, abs=0.3)
        final = pressure.rows["pressure"][-50:].mean(axis=0)
        assert final == pytest.approx(plan.pressure_pa[-1], abs=1.5e3)


def test_impact_taps_ring_the_link(sessions):
    for _, data, events in sessions["popup_impact"]:
        t = _seconds(data[T.ACCEL].log_time)
        a = data[T.ACCEL].rows["acceleration"]
        taps = [te for te, e in events if e.kind == EventKind.PLAN_STEP and e.label == "tap"]
        assert len(taps) == 3
        for t_tap in taps:
            after = a[(t > t_tap + 0.02) & (t < t_tap + 0.3)]
            before = a[(t > t_tap - 0.3) & (t < t_tap - 0.01)]
            assert after.std(axis=0).max() > 20 * before.std(axis=0).max()


def test_static_loop_follows_the_link_model(sessions, popup):
    """Vertical tip positions averaged over each SETTLED hold follow the quasi-static link model
    (``prbm.static_loading_curve``: link 2 elastic below M_w, wrinkled and hysteretic above) through the
    whole load history, within the tracker's noise averaged over a hold; the loading/unloading loop of the
    second repetition is the model's."""
    ((plan, data, events),) = sessions["popup_static"]
    tracker = data[T.TRACKER]
    t, z = _seconds(tracker.log_time), tracker.rows["position"][:, 2]
    ok = ~tracker.rows["missing"]
    holds = [(te, e.value) for te, e in events if e.kind == EventKind.SETTLED]
    heights = np.array([z[ok & (t >= t0) & (t < t0 + hold)].mean() for t0, hold in holds])
    loads = np.asarray(plan.parameters["loads_kg"])
    n = len(loads)
    cycle = np.concatenate([loads, loads[::-1][1:], loads, loads[::-1][1:]])
    assert len(heights) == len(cycle)
    link2 = popup.links[0]
    table = popup.link_table(link2.name)
    k = np.interp(plan.parameters["pressure_pa"], table.pressure_pa, table.stiffness_nm_per_rad)
    arm, own = 0.590, 0.868  # link 2 hinge (D-H row d22) to tip; link 2's own moment there (N·m)
    torque = np.concatenate([[own], own + cycle * 9.81 * arm])  # from the virgin link at rest
    m_w = prbm.wrinkling_moment(plan.parameters["pressure_pa"], link2.radius_m)
    h = link2.hysteresis
    delta = prbm.static_loading_curve(torque, k, h.delta_h_rad, h.tau_y_nm, m_w)[1:]
    model = (delta - delta[0]) * arm  # tip drop from the first hold
    measured = heights[0] - heights
    noise = popup.sensors.tracker.noise_m / np.sqrt(0.5 * 40)  # a 0.5 s hold of 40 Hz frames
    np.testing.assert_allclose(measured, model, atol=6 * noise + 0.05e-3)
    second = slice(2 * n - 1, None)

    def loop(x):  # widest gap between the loading and unloading branches at equal loads
        return np.abs(x[: n - 1] - x[n:][::-1]).max()

    assert loop(measured[second]) == pytest.approx(loop(model[second]), abs=4 * noise)
    assert loop(model[second]) > 0.4e-3  # a loop the tracker resolves


def test_deploy_pressure_checks_pass(sessions):
    ((plan, data, _),) = sessions["popup_deploy"]
    pressure = data[T.PRESSURE]
    t, p = _seconds(pressure.log_time), pressure.rows["pressure"]
    results = pp.verify_pressure_checks(pp.pressure_checks(plan.events), t, p)
    assert [r[0] for r in results] == [0, 1] and all(r[3] for r in results)
    first_check = pp.pressure_checks(plan.events)[0][0]
    assert p[t < first_check, 1].max() < 1e3  # link 2 stays deflated until link 1 is full


def test_a_simulated_reach_ends_where_the_plan_does(sessions):
    ((plan, data, events),) = sessions["popup_reach"]
    joints = data[T.JOINT_STATE]
    t = _seconds(joints.log_time)
    (end,) = [at for at, e in events if e.kind == EventKind.SETTLED and e.index == 1]
    held = joints.rows["position"][(t > end) & (t < end + 2.0)]
    # within the drives' droop under 2 kg (their position loops hold the load with a steady error); q1, the
    # base yaw, holds no gravity load: at its goal
    np.testing.assert_allclose(held.mean(axis=0), plan.goal_q[-1], atol=0.015)
    assert abs(held[:, 0].mean() - plan.goal_q[-1, 0]) < 1e-3
    slope = np.polyfit(t[(t > end) & (t < end + 2.0)] - end, held, 1)[0]
    assert np.abs(slope).max() < 1e-4, "still during the hold (no creep at the path's last profile speed)"
