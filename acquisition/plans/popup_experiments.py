"""The POPUP arm's test experiments of seed 001, expanded into plans (one plan per session):

- ``popup_static``: link 2 held horizontal as a cantilever, tip masses loaded then unloaded at each pressure,
  a settled hold at every load, repeated (Fig. 7: load–displacement with hysteresis);
- ``popup_impact``: at each pressure a hammer tap on link 2 and its free oscillation recorded by the tip
  accelerometer (Table 1: damped frequency and log-decrement damping);
- ``popup_deploy``: links deflated with valves closed, link 1 inflated to its set point, then link 2 once
  link 1's transducer has reached it (PLAN_STEP 'pressure-check' events, verified by
  :func:`verify_pressure_checks`);
- ``popup_survey``: settled poses drawn over the workspace (ASSUMED: the seed has no data campaign), the
  static points the pipeline registers the tracker on;
- ``popup_reach``: the velocity-law reach of Figs. 12–13 (eq. 3), planned on the rigid model, followed with a
  2 kg payload at 60 kPa, a settled hold at the start and at the target (SETTLED 0 and 1).

Parameters come from ``configs/experiments/popup_*.yaml`` (``experiments.load_experiment``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.safety import SafetyChecker
from acquisition.schemas.events import Event, EventKind
from models.prbm import collapse_moment
from models.robot import Hysteresis, RobotDescription
from models.statics import gravity_moments
from models.trajectories import velocity_law_reach

KPA, GRAM = 1e3, 1e-3
PRESSURE_CHECK = "pressure-check"


RIGID_FACTOR = 1000.0  # a "fixed joint": stiffness and damping × 1000, no hysteresis


def bench_robot(robot: RobotDescription, params: dict) -> RobotDescription:
    """The robot as set up for the test (the paper's link tests ran on a bare link on a fixed joint):
    masses named in ``without_masses`` taken off, links named in ``rigid_links`` made ``RIGID_FACTOR`` times
    stiffer without hysteresis, and with ``fixed_joints`` the drives too (``RIGID_FACTOR`` stiffer, no
    backlash: their droop under the test loads would add to the link's deflection), so the tip sees only the
    link under test."""
    drop = set(params.get("without_masses") or [])
    rigid = set(params.get("rigid_links") or [])
    unknown = (drop - {m.name for m in robot.masses}) | (rigid - {link.name for link in robot.links})
    if unknown:
        raise ValueError(f"robot {robot.name!r} has no mass(es) or link(s) {sorted(unknown)}")
    links = [
        link.model_copy(
            update={
                "table": robot.link_table(link.name).scaled(RIGID_FACTOR),
                "hysteresis": Hysteresis(delta_h_rad=0.0, tau_y_nm=link.hysteresis.tau_y_nm),
            }
        )
        if link.name in rigid
        else link
        for link in robot.links
    ]
    update = {"masses": [m for m in robot.masses if m.name not in drop], "links": links}
    if params.get("fixed_joints") and robot.servo is not None:
        update["servo"] = robot.servo.model_copy(
            update={
                "stiffness_per_p_gain_nm_per_rad": robot.servo.stiffness_per_p_gain_nm_per_rad * RIGID_FACTOR,
                "backlash_rad": 0.0,
            }
        )
    return robot.model_copy(update=update)


def _builder(name: str, robot: RobotDescription, parameters: dict) -> PlanBuilder:
    return PlanBuilder(name, robot.name, len(robot.actuated_joints), robot.pneumatics.channels, parameters)


def _pose(params: dict) -> np.ndarray:
    return np.radians(np.asarray(params["pose_deg"], float))


def static_loads_kg(robot: RobotDescription, params: dict, pressure_pa: float) -> np.ndarray:
    """Tip masses of one pressure's static test: ``load_steps`` equal steps from 0 up to the mass that bends
    the link under test to ``max_collapse_fraction`` of its collapse moment M_c(p) (own weight included,
    at the test pose, as the safety checker computes it), rounded to whole grams like a set of weights.

    The paper gives no loads; Fig. 7 runs past M_w into the non-linear range at every pressure, so the loads
    scale with M_c ∝ p. Points below M_w (the linear range Table 1's k is fitted on) are then spread evenly.
    """
    link = next(ln for ln in robot.links if ln.name == params["link"])
    rows = [r.joint for r in robot.dh_rows()]
    axes = [rows.index(v) for v in link.virtual_joints]
    q = _pose(params)
    own, per_kg = (np.linalg.norm(gravity_moments(robot, q, payload_kg=kg)[axes]) for kg in (0.0, 1.0))
    top = params["max_collapse_fraction"] * collapse_moment(pressure_pa, link.radius_m)
    max_kg = (top - own) / (per_kg - own)  # the moment is affine in the tip mass at a fixed pose
    if max_kg <= 0:
        raise ValueError(f"{link.name} at {pressure_pa / KPA:g} kPa: its own weight passes the top load")
    return np.round(np.linspace(0.0, max_kg, params["load_steps"] + 1), 3)


def static_test(robot: RobotDescription, params: dict) -> list[Plan]:
    """One plan per pressure: loading through :func:`static_loads_kg` then unloading back, a SETTLED hold at
    every load (index = point number in the plan), each repetition bracketed by REPETITION_START/END;
    PLAN_STEP events 'loading'/'unloading' mark the branches."""
    plans = []
    for kpa in params["pressures_kpa"]:
        loads = static_loads_kg(robot, params, kpa * KPA)
        branches = (("loading", loads), ("unloading", loads[::-1][1:]))
        cell = {
            "experiment": "popup_static",
            "pressure_pa": kpa * KPA,
            "link": params["link"],
            "loads_kg": loads.tolist(),
            "allow_wrinkling": bool(params.get("allow_wrinkling", False)),
        }
        b = _builder(f"popup_static/{kpa:g}kPa", robot, cell)
        b.goto(_pose(params)).pressure(kpa * KPA).payload(float(loads[0])).wait(params["pressure_settle_s"])
        point = 0
        for rep in range(params["repetitions"]):
            b.mark(EventKind.REPETITION_START, rep, "static")
            for label, branch in branches:
                b.mark(EventKind.PLAN_STEP, rep, label)
                for kg in branch:
                    b.payload(float(kg)).settle(params["settle_s"], index=point, hold_s=params["hold_s"])
                    point += 1
            b.mark(EventKind.REPETITION_END, rep, "static")
        plans.append(b.build())
    return plans


def impact_test(robot: RobotDescription, params: dict) -> list[Plan]:
    """One plan per pressure: settle, then ``taps`` hammer taps, each followed by ``record_s`` of free
    oscillation and bracketed by REPETITION_START/END."""
    plans = []
    for kpa in params["pressures_kpa"]:
        impulse = params["tap_impulse_nms"]
        cell = {"experiment": "popup_impact", "pressure_pa": kpa * KPA, "tap_impulse_nms": impulse}
        b = _builder(f"popup_impact/{kpa:g}kPa", robot, cell)
        b.goto(_pose(params)).pressure(kpa * KPA).payload(0.0).settle(params["settle_s"])
        for rep in range(params["taps"]):
            b.mark(EventKind.REPETITION_START, rep, "impact")
            b.tap(impulse).wait(params["record_s"])
            b.mark(EventKind.REPETITION_END, rep, "impact")
        plans.append(b.build())
    return plans


def fill_time_s(robot: RobotDescription, time_constants: float) -> float:
    """Estimated time for a link to reach its set point: regulator dead time + ``time_constants`` lags."""
    pn = robot.pneumatics
    return pn.regulator_dead_time_s + time_constants * pn.regulator_time_constant_s


def deployment(robot: RobotDescription, params: dict) -> list[Plan]:
    """Links at 0 Pa with valves closed; channel 0 opened to its set point, a settle and a 'pressure-check'
    PLAN_STEP (index = channel, value = set point) after the estimated fill time, its valve closed; then
    channel 1; then the deployed arm held still (SETTLED 0: a static point)."""
    set_points = np.asarray(params["set_points_kpa"], float) * KPA
    channels = robot.pneumatics.channels
    if len(set_points) != channels:
        raise ValueError(f"popup_deploy: set_points_kpa needs {channels} values, got {len(set_points)}")
    fill_s = fill_time_s(robot, params["fill_time_constants"])
    cell = {
        "experiment": "popup_deploy",
        "set_points_pa": set_points.tolist(),
        "fill_s": fill_s,
    }
    b = _builder("popup_deploy/" + "-".join(f"{p / KPA:g}" for p in set_points) + "kPa", robot, cell)
    pressure, valves = np.zeros(channels), np.zeros(channels, bool)
    b.goto(_pose(params)).pressure(pressure, valves).payload(0.0).wait(params["deflated_s"])
    for ch in params["order"]:
        pressure[ch], valves[ch] = set_points[ch], True
        b.pressure(pressure, valves).mark(EventKind.PLAN_STEP, ch, "inflate", value=float(set_points[ch]))
        # settle: in real time the plan goes on only once the link holds its set point (the seed's check of
        # link 1's transducer before link 2), or stops after the runner's settle timeout
        b.settle(fill_s).mark(EventKind.PLAN_STEP, ch, PRESSURE_CHECK, value=float(set_points[ch]))
        valves[ch] = False  # normally-closed valves: the supply is cut once the link is full
        b.pressure(pressure, valves)
    b.settle(0.0, index=0, hold_s=params["hold_s"])  # the deployed arm at rest: one static point
    return [b.build()]


def target_reach(robot: RobotDescription, params: dict) -> list[Plan]:
    """One plan: links inflated to ``pressure_kpa``, the arm at ``q0_deg``, the payload hung and a settled
    hold (SETTLED 0), the joint path of :func:`models.trajectories.velocity_law_reach` to ``target_mm`` every
    ``dt_s`` (bracketed by REPETITION_START/END 'reach'), and a settled hold at the end (SETTLED 1)."""
    pressure, payload = params["pressure_kpa"] * KPA, float(params["payload_kg"])
    q0, target = np.radians(params["q0_deg"]), np.asarray(params["target_mm"], float) * 1e-3
    law = (params["v0_m_s"], params["a0_m_s2"])
    t, q = velocity_law_reach(
        robot.chain(), q0, target, *law, dt=params["dt_s"], tol_m=params["tolerance_mm"] * 1e-3
    )
    if len(t) < 2:
        raise ValueError(
            f"popup_reach: the tip is already within {params['tolerance_mm']:g} mm of the target"
        )
    cell = {"experiment": "popup_reach", "pressure_pa": pressure, "payload_kg": payload,
            "target_m": target.tolist(), "allow_wrinkling": bool(params["allow_wrinkling"])}  # fmt: skip
    b = _builder(f"popup_reach/{params['pressure_kpa']:g}kPa-{payload * 1e3:g}g", robot, cell)
    b.goto(q0).pressure(pressure).payload(0.0).settle(params["settle_s"])
    b.payload(payload).settle(params["settle_s"], index=0, hold_s=params["hold_s"])
    b.mark(EventKind.REPETITION_START, 0, "reach").follow(t, q, np.gradient(q, t, axis=0))
    # the target again at the drives' own speed: the path's last set-points carry the law's last few mm/s
    # as their profile speed, at which a drive would close what it lags behind (a creep of ≈ 2 mrad/s)
    b.mark(EventKind.REPETITION_END, 0, "reach").goto(q[-1])
    b.settle(params["settle_s"], index=1, hold_s=params["hold_s"])
    return [b.build()]


MAX_DRAWS = 100  # draws per survey point before the joint box is deemed unsafe at these loads


def survey(robot: RobotDescription, params: dict, seed: int = 0) -> list[Plan]:
    """One plan of ``points`` settled static points (SETTLED index = point): joint angles drawn uniformly in
    the ``joints_deg`` box, link pressures uniformly in ``pressure_kpa``, payloads from ``payloads_g``; a pose
    the safety checker refuses at its pressure and payload (the tip outside the workspace, a link past M_w)
    is drawn again. The joints move at ``move_speed_rad_s``, then settle and hold."""
    rng = np.random.default_rng(seed)
    check = SafetyChecker(robot)
    lo, hi = (np.radians(params["joints_deg"][k]) for k in ("min", "max"))
    p_lo, p_hi = (v * KPA for v in params["pressure_kpa"])
    masses = np.asarray(params["payloads_g"], float) * GRAM
    channels = robot.pneumatics.channels
    b = _builder("popup_survey/" + f"{params['points']}points", robot,
                 {"experiment": "popup_survey", "seed": seed, "points": params["points"]})  # fmt: skip
    previous = None
    for point in range(params["points"]):
        for _ in range(MAX_DRAWS):
            q, pressure, kg = rng.uniform(lo, hi), rng.uniform(p_lo, p_hi), float(rng.choice(masses))
            if not check.check_state(np.zeros(1), q[None], np.full((1, channels), pressure), kg):
                break
        else:
            raise ValueError(f"popup_survey: no safe pose in {MAX_DRAWS} draws in joints_deg at these loads")
        b.pressure(pressure).payload(kg).goto(q, params["move_speed_rad_s"])
        # the joints travel at the move speed first; settling starts when they arrive
        if previous is not None:
            b.wait(float(np.abs(q - previous).max()) / params["move_speed_rad_s"])
        b.settle(params["settle_s"], index=point, hold_s=params["hold_s"])
        previous = q
    return [b.build()]


def pressure_checks(events: list[tuple[float, Event]]) -> list[tuple[float, int, float]]:
    """The (time, channel, set point Pa) of every pressure check among ``events``: a plan's (plan seconds) or
    a recorded session's (its log times), so a deployment is verified the same way on both."""
    return [
        (t, e.index, e.value)
        for t, e in events
        if e.kind == EventKind.PLAN_STEP and e.label == PRESSURE_CHECK
    ]


def verify_pressure_checks(
    checks: list[tuple[float, int, float]], t: np.ndarray, pressure_pa: np.ndarray, tolerance: float = 0.05
) -> list[tuple[int, float, float, bool]]:
    """At every check (:func:`pressure_checks`), the last measured pressure (``t`` on the checks' clock,
    ``pressure_pa`` (n, C)) of its channel against the set point: (channel, set point, measured, within
    ``tolerance`` of it)."""
    out = []
    for at, ch, target in checks:
        i = int(np.searchsorted(t, at, side="right")) - 1
        measured = float(pressure_pa[i, ch]) if i >= 0 else math.nan
        out.append((ch, target, measured, abs(measured - target) <= tolerance * target))
    return out


EXPERIMENTS: dict[str, Callable[[RobotDescription, dict], list[Plan]]] = {
    "popup_static": static_test,
    "popup_impact": impact_test,
    "popup_deploy": deployment,
    "popup_reach": target_reach,
    "popup_survey": survey,
}
