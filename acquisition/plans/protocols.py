"""Protocols from the seeds, expanded into plans (one plan per session) from ``configs/protocols/*.yaml``.

- ``experiment1``: linear, curve and square × payloads × VSL pressures and the rigid arm, repeated;
- ``experiment2``: the curve at two (payload, pressure) cases, model-based vs compensated commands;
- ``campaign``: seed 000's data campaign, random pressure, joint position and payload per settled point.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.schemas.events import EventKind
from models import kinematics, trajectories
from models.robot import AnthropomorphicKinematics, RobotDescription

PROTOCOL_DIR = Path(__file__).resolve().parents[2] / "configs" / "protocols"
BAR, GRAM, MM = 1e5, 1e-3, 1e-3


def load_protocol(name_or_path: str | Path, **overrides: Any) -> dict:
    """A protocol's parameters: ``configs/protocols/<name>.yaml`` (or a path), with keyword overrides for
    keys it already has (a misspelt override is an error, not silently ignored)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = PROTOCOL_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in PROTOCOL_DIR.glob("*.yaml")))
        raise FileNotFoundError(f"no protocol {name_or_path!r} (known: {known})")
    params = yaml.safe_load(path.read_text()) or {}
    unknown = set(overrides) - set(params)
    if unknown:
        raise ValueError(f"{path.name}: no parameter(s) {sorted(unknown)}")
    return params | overrides


def arm_lengths(robot: RobotDescription) -> kinematics.ArmLengths:
    kin = robot.kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(
            f"robot {robot.name!r} is not an anthropomorphic arm (Experiment 1 needs the VSL arm)"
        )
    return kinematics.ArmLengths(kin.l1_m, kin.l2_m, kin.l3_m)


def _builder(name: str, robot: RobotDescription, parameters: dict) -> PlanBuilder:
    return PlanBuilder(name, robot.name, len(robot.actuated_joints), robot.pneumatics.channels, parameters)


def experiment1(vsl: RobotDescription, rigid: RobotDescription | None, params: dict) -> list[Plan]:
    """One plan per (arm, payload, trajectory): set pressure and payload, settle, then the repetitions,
    each bracketed by REPETITION_START/END events and followed by a slow return to the start point."""
    arms: list[tuple[RobotDescription, float, str]] = [
        (vsl, p * BAR, f"{vsl.name}-{p:g}bar") for p in params["pressures_bar"]
    ]
    if params["rigid_arm"] and rigid is not None:
        arms.append((rigid, 0.0, rigid.name))
    plans = []
    for robot, pressure_pa, arm in arms:
        for name in params["trajectories"]:
            for grams in params["payloads_g"]:
                cell = {
                    "trajectory": name,
                    "arm": arm,
                    "pressure_pa": pressure_pa,
                    "payload_kg": grams * GRAM,
                }
                plans.append(
                    _trajectory_plan(
                        f"experiment1/{name}/{arm}/{grams:g}g",
                        robot,
                        params,
                        {"protocol": "experiment1", **cell},
                    )
                )
    return plans


COMMANDS = ("ik", "static", "hybrid")  # Experiment 2's command modes (see acquisition.plans.compensation)


def experiment2(vsl: RobotDescription, rigid: RobotDescription | None, params: dict) -> list[Plan]:
    """Seed 000's Experiment 2: the curve at each (payload, pressure) case, commanded by the model-based IK
    (``ik``), the grey-box static compensation (``static``, ours) and the hybrid inverse network (``hybrid``);
    the rigid-link arm with the model-based IK at each case's payload. The plans' goals are always the IK of
    the desired path; ``parameters["commands"]`` says which compensator turns them into commands."""
    unknown = set(params["commands"]) - set(COMMANDS)
    if unknown:
        raise ValueError(
            f"experiment2: unknown command mode(s) {sorted(unknown)} (known: {', '.join(COMMANDS)})"
        )
    name = params["trajectory"]
    cells = []
    for case in params["cases"]:
        grams, bar = case["payload_g"], case["pressure_bar"]
        cells += [(vsl, bar * BAR, f"{vsl.name}-{bar:g}bar", grams, mode) for mode in params["commands"]]
        if params["rigid_arm"] and rigid is not None:
            cells.append((rigid, 0.0, rigid.name, grams, "ik"))
    plans, seen = [], set()
    for robot, pressure_pa, arm, grams, mode in cells:
        plan_name = f"experiment2/{name}/{arm}/{grams:g}g/{mode}"
        if plan_name in seen:  # the rigid arm at a payload two cases share
            continue
        seen.add(plan_name)
        cell = {"trajectory": name, "arm": arm, "pressure_pa": pressure_pa, "payload_kg": grams * GRAM}
        parameters = {"protocol": "experiment2", "commands": mode, **cell}
        plans.append(_trajectory_plan(plan_name, robot, params | {"trajectories": [name]}, parameters))
    return plans


def _trajectory_plan(plan_name: str, robot: RobotDescription, params: dict, cell: dict) -> Plan:
    """Set pressure and payload, settle, then the repetitions of one Experiment 1/2 trajectory."""
    path = trajectories.experiment1(
        cell["trajectory"],
        arm_lengths(robot),
        speed=params["speed_m_s"],
        n_per_segment=params["points_per_segment"],
    )
    b = _builder(plan_name, robot, cell)
    b.goto(path.q[0], params["return_speed_rad_s"]).pressure(cell["pressure_pa"]).payload(cell["payload_kg"])
    b.settle(params["settle_s"])
    for rep in range(params["repetitions"]):
        b.mark(EventKind.REPETITION_START, rep, cell["trajectory"])
        b.follow(path.t, path.q, path.qd)
        b.wait(0.5).mark(EventKind.REPETITION_END, rep, cell["trajectory"])
        b.goto(path.q[0], params["return_speed_rad_s"]).wait(params["rest_s"])
    return b.build()


def campaign(robot: RobotDescription, params: dict, benches: int = 1, seed: int = 0) -> list[Plan]:
    """The random static-point campaign, its points dealt to ``benches`` plans (parallel twin benches, or
    sessions on one robot). Points are tip targets drawn uniformly in the workspace box, turned into joint
    positions by the rigid IK (elbow up); pressures uniform in the range, payloads from the list."""
    rng = np.random.default_rng(seed)
    n = int(params["points"])
    lo, hi = (np.asarray(params["workspace_mm"][k], float) * MM for k in ("min", "max"))
    targets = rng.uniform(lo, hi, size=(n, 3))
    q = kinematics.vsl_ik(targets, arm_lengths(robot), 1)
    p_lo, p_hi = (v * BAR for v in params["pressure_bar"])
    pressure = rng.uniform(p_lo, p_hi, size=n)
    payload = rng.choice(np.asarray(params["payloads_g"], float) * GRAM, size=n)
    plans = []
    for k, idx in enumerate(np.array_split(np.arange(n), min(benches, n))):
        b = _builder(
            f"campaign/bench{k:03d}", robot, {"protocol": "campaign", "seed": seed, "points": len(idx)}
        )
        previous = q[idx[0]]
        for point in idx:
            b.pressure(pressure[point]).payload(payload[point]).goto(q[point], params["move_speed_rad_s"])
            # the joints travel at the move speed first; settling starts when they arrive
            b.wait(float(np.abs(q[point] - previous).max()) / params["move_speed_rad_s"])
            b.settle(params["settle_s"], index=int(point), hold_s=params["hold_s"])
            previous = q[point]
        plans.append(b.build())
    return plans


def expand_protocol(
    protocol: str | Path, overrides: dict | None = None, benches: int = 1, seed: int = 0
) -> tuple[dict[str, RobotDescription], list[Plan], dict]:
    """A protocol's robots (by name, as set up for it), its plans and its parameters (with overrides).
    ``benches``: how many parallel benches the campaign's points are dealt to."""
    from acquisition.plans import popup_protocols
    from models.robot import load_robot

    params = load_protocol(protocol, **(overrides or {}))
    kind = Path(protocol).stem
    robots = {params["robot"]: load_robot(params["robot"])}
    if kind in ("experiment1", "experiment2"):
        if params["rigid_arm"]:
            robots[params["rigid_robot"]] = load_robot(params["rigid_robot"])
        expand = experiment1 if kind == "experiment1" else experiment2
        plans = expand(robots[params["robot"]], robots.get(params["rigid_robot"]), params)
    elif kind == "campaign":
        plans = campaign(robots[params["robot"]], params, benches=benches, seed=seed)
    elif kind in popup_protocols.PROTOCOLS:
        robot = popup_protocols.bench_robot(robots[params["robot"]], params)
        robots = {robot.name: robot}
        plans = popup_protocols.PROTOCOLS[kind](robot, params)
    else:
        known = ", ".join(["experiment1", "experiment2", "campaign", *popup_protocols.PROTOCOLS])
        raise ValueError(f"no plans for protocol {protocol!r} ({known})")
    return robots, plans, params
