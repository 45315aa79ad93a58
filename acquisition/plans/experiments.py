"""Experiments from the seeds, expanded into plans (one plan per session) from ``configs/experiments/*.yaml``.

- ``experiment1``: linear, curve and square × payloads × VSL pressures and the rigid arm, repeated;
- ``experiment2``: the curve at two (payload, pressure) cases, model-based vs compensated commands;
- ``campaign``: seed 000's data campaign, random pressure, joint position and payload per settled point.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from acquisition.errors import AcquisitionError
from acquisition.plans.plan import Plan, PlanBuilder
from acquisition.schemas.events import EventKind
from models import kinematics, trajectories
from models.robot import AnthropomorphicKinematics, RobotDescription
from models.yaml_files import read_yaml

EXPERIMENT_DIR = Path(__file__).resolve().parents[2] / "configs" / "experiments"
BAR, GRAM, MM = 1e5, 1e-3, 1e-3


class ExperimentError(AcquisitionError, ValueError):
    """An experiment file or parameter that cannot be used: names the file (or ``--set``), the key and why."""


def load_experiment(name_or_path: str | Path, **overrides: Any) -> dict:
    """An experiment's parameters: ``configs/experiments/<name>.yaml`` (or a path), with keyword
    overrides for keys it already has (a misspelt override is an error, not silently ignored).
    FileNotFoundError for an unknown name or a missing file; :class:`ExperimentError` for a file that is not a
    mapping of parameters."""
    path = Path(name_or_path)
    if not path.suffix:
        path = EXPERIMENT_DIR / f"{name_or_path}.yaml"
    if path.is_dir():
        raise ExperimentError(
            f"{path}: a folder, not an experiment file (YAML, like configs/experiments/*.yaml)"
        )
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in EXPERIMENT_DIR.glob("*.yaml")))
        raise FileNotFoundError(
            f"no experiment {str(name_or_path)!r} (known: {known}; or a YAML file's path)"
        )
    shown = _shown(path)
    params = read_yaml(path, ExperimentError, shown)
    if not isinstance(params, dict) or not params:
        found = "nothing" if not params else f"a {type(params).__name__}"
        raise ExperimentError(f"{shown}: expected a mapping of parameters (like configs/experiments/*.yaml), "
                            f"found {found}")  # fmt: skip
    if unknown := sorted(set(overrides) - set(params), key=str):
        raise ExperimentError(f"--set {unknown[0]}: {shown} has no parameter {unknown[0]!r} (its parameters: "
                            f"{', '.join(map(str, params))})")  # fmt: skip
    return params | overrides


def _shown(path: Path) -> str:
    """An experiment file as messages name it: the shipped ones by file name, the user's by path."""
    return path.name if path.parent == EXPERIMENT_DIR else str(path)


# How experiment parameters are checked against the shipped file of their experiment (the schema by example):
# a value must be of its default's kind (true/false, number, text, list, mapping), numbers finite and ≥ 0.
COUNTS = {"points", "repetitions", "points_per_segment", "taps", "load_steps"}  # integers ≥ 1
INDICES = {"order"}  # integers ≥ 0 (pressure channels)
MAX_COUNT = 1_000_000  # far past any experiment (the paper's campaign: 17,568 points)
SIGNED = {"pose_deg", "workspace_mm", "q0_deg", "target_mm", "joints_deg"}  # may be negative
POSITIVE = {"speed_m_s", "move_speed_rad_s", "return_speed_rad_s", "fill_time_constants", "tap_impulse_nms",
            "max_collapse_fraction", "v0_m_s", "a0_m_s2", "dt_s", "tolerance_mm"}  # fmt: skip
MAY_BE_EMPTY = {"without_masses", "rigid_links"}
# Physical ranges (the parameter's own unit), inclusive: past them a value is a typo, and a plan built from it
# would wait, move or last longer than any bench runs (1e308 s of settling, a tip crawling at 1e-300 m/s).
MAX_WAIT_S = 3600.0  # one wait of a plan (settle, hold, rest, record): an hour is past any bench's settling
BOUNDS = {
    "speed_m_s": (1e-3, 1.0), "v0_m_s": (1e-3, 1.0), "a0_m_s2": (1e-3, 10.0),  # tip: 1 mm/s to 1 m/s
    # joints: an XM430 turns ≈ 4.8 rad/s unloaded; a plan may ask more (the servo then lags: tests do so on
    # purpose), but past 50 rad/s it is a typo
    "move_speed_rad_s": (1e-3, 50.0), "return_speed_rad_s": (1e-3, 50.0),
    "dt_s": (1e-3, 1.0),  # a set-point every 1 ms (past the drives' rate) to 1 s
    "tolerance_mm": (1e-3, 1000.0), "max_collapse_fraction": (0.0, 1.0), "fill_time_constants": (0.0, 100.0),
    "tap_impulse_nms": (0.0, 10.0),  # a hand-held hammer: ≈ 0.02 N·m·s
    "pressures_bar": (0.0, 10.0), "pressure_bar": (0.0, 10.0),  # the lab's supply: 6 bar; 10 bar is past it
    "pressures_kpa": (0.0, 1000.0), "pressure_kpa": (0.0, 1000.0), "set_points_kpa": (0.0, 1000.0),
    "payloads_g": (0.0, 10_000.0), "payload_g": (0.0, 10_000.0), "payload_kg": (0.0, 10.0),  # ≤ 10 kg
    "workspace_mm": (-10_000.0, 10_000.0), "target_mm": (-10_000.0, 10_000.0),  # within 10 m of the base
    "pose_deg": (-360.0, 360.0), "q0_deg": (-360.0, 360.0), "joints_deg": (-360.0, 360.0),
    "points": (1, MAX_COUNT), "repetitions": (1, 1000), "points_per_segment": (1, 10_000), "taps": (1, 1000),
    "load_steps": (1, 1000), "order": (0, 64),
}  # fmt: skip
MAX_LIST_ITEMS = 100  # values in one list parameter (payloads, pressures): the longest shipped has 9
# What an expanded experiment may amount to, checked before any plan is built (sizes) and before any run
# (durations): 100,000 set-points (≈ 6× the paper's campaign) build in ≈ 10 s (30 s on a busy machine); a
# week of bench time is ≈ 10× the paper's campaign.
MAX_SET_POINTS = 100_000
POOLED = {"campaign": {"payloads_g"}, "popup_survey": {"payloads_g"}}  # lists drawn from, not gone through
MAX_EXPERIMENT_S = 7 * 86400.0
CHOICES = {"visit_order": ("drawn", "shuffled", "reversed")}  # text parameters with a fixed set of values
REPEATS = ("shuffled", "reversed")  # visit orders of a campaign's repeat: its sessions are named apart
SHUFFLE_STREAM = 0x5EED  # the shuffled repeat's own random stream: (seed, this, bench), apart from the draw
RANGES = {"campaign": ("pressure_bar", "workspace_mm"), "popup_survey": ("pressure_kpa", "joints_deg")}
FIXED_LENGTH = {"pose_deg", "pressure_bar", "workspace_mm", "set_points_kpa", "q0_deg", "target_mm",
                "pressure_kpa", "joints_deg"}  # fmt: skip  # as many values as the default


def check_experiment(kind: str, params: dict, source: str, overridden=()) -> None:
    """``params`` of experiment ``kind`` against its shipped file: the same keys, each value of the default's
    kind and range. :class:`ExperimentError` names the first that is not (``source``: the file; a key in
    ``overridden`` is named as ``--set key``)."""
    default_path = EXPERIMENT_DIR / f"{kind}.yaml"
    defaults = yaml.safe_load(default_path.read_text(encoding="utf-8"))
    if missing := [k for k in defaults if k not in params]:
        needed = f"every parameter of {default_path.name} is needed"
        raise ExperimentError(f"{source}: missing parameter(s) {missing} ({needed})")
    if unknown := sorted(set(params) - set(defaults), key=str):
        raise ExperimentError(f"{source}: unknown parameter(s) {unknown} (those of {kind}: "
                            f"{', '.join(defaults)})")  # fmt: skip
    for key, default in defaults.items():
        where = f"--set {key}" if key in overridden else f"{source}: {key}"
        _check_value(key, params[key], default, where)
    if kind in RANGES:  # a draw's pressure range [low, high] and its box, min below max on every axis
        pressure, box = RANGES[kind]
        lo, hi = params[pressure]
        if lo > hi or any(a >= b for a, b in zip(params[box]["min"], params[box]["max"], strict=True)):
            where = "--set" if {pressure, box} & set(overridden) else source
            raise ExperimentError(
                f"{where}: {pressure} must be [low, high] and {box}'s min below its max on every axis"
            )
    if kind == "popup_deploy" and any(ch >= len(params["set_points_kpa"]) for ch in params["order"]):
        where = "--set order" if "order" in overridden else f"{source}: order"
        raise ExperimentError(f"{where}: {params['order']}: a channel of set_points_kpa (0 to "
                            f"{len(params['set_points_kpa']) - 1})")  # fmt: skip


def check_size(kind: str, params: dict, source: str, overridden=()) -> None:
    """Before any plan is built: the experiment's set-points (an upper bound: the product of its counts and
    of the lengths of the lists it goes through, × 4 segments of a path) within :data:`MAX_SET_POINTS`."""
    factors = {k: v for k, v in params.items() if k in COUNTS and isinstance(v, int)}
    skip = FIXED_LENGTH | POOLED.get(kind, set())
    factors |= {k: len(v) for k, v in params.items() if isinstance(v, list) and k not in skip and v}
    size = math.prod(factors.values()) * (4 if "points_per_segment" in factors else 1)
    if size > MAX_SET_POINTS:
        where = "--set" if set(factors) & set(overridden) else source
        raise ExperimentError(f"{where}: {' × '.join(factors)} make up to {size:,} set-points (at most "
                            f"{MAX_SET_POINTS:,}: a smaller experiment, or several)")  # fmt: skip


def check_plans(plans: list[Plan], source: str) -> None:
    """Once built, before any run: the plans' bench time within :data:`MAX_EXPERIMENT_S` (finite, and no
    run that outlasts a lab's week)."""
    total = sum(p.duration_s for p in plans)
    if not math.isfinite(total) or total > MAX_EXPERIMENT_S:
        raise ExperimentError(f"{source}: the plans last {total / 86400:,.3g} days of bench time (at most "
                            f"{MAX_EXPERIMENT_S / 86400:g}: shorter waits, fewer points)")  # fmt: skip


def _check_value(key: str, value, default, where: str) -> None:
    """``value`` of parameter ``key`` against its ``default`` (recursively into lists and mappings)."""

    def fail(expected: str) -> None:
        raise ExperimentError(f"{where}: {value!r:.60}: expected {expected}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            fail("true or false")
    elif isinstance(default, int | float):
        number = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        low, high = BOUNDS.get(key, (-math.inf, MAX_WAIT_S) if key.endswith("_s") else (-math.inf, math.inf))
        if key in COUNTS or key in INDICES:
            low = max(low, 1 if key in COUNTS else 0)
            if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
                fail(f"an integer from {low} to {high:,}")
        elif not number or (key not in SIGNED and value < 0) or (key in POSITIVE and value <= 0):
            fail("a number > 0" if key in POSITIVE else "a number" if key in SIGNED else "a number ≥ 0")
        elif not low <= value <= high:
            fail(f"a number from {low:g} to {high:g}" if low > -math.inf else f"a number up to {high:g}")
    elif isinstance(default, str):
        if key in CHOICES and value not in CHOICES[key]:
            fail(" or ".join(CHOICES[key]))
        if not isinstance(value, str) or not value:
            fail("a name (text)")
    elif isinstance(default, list):
        if not isinstance(value, list):
            fail(f"a [list] like {default}")
        if default and not value and key not in MAY_BE_EMPTY:
            fail(f"a non-empty [list] like {default}")
        if key in FIXED_LENGTH and len(value) != len(default):
            fail(f"{len(default)} values, like {default}")
        if len(value) > MAX_LIST_ITEMS:
            fail(f"at most {MAX_LIST_ITEMS} values")
        for item in value if default else ():
            _check_value(key, item, default[0], where)
    elif isinstance(default, dict):
        if not isinstance(value, dict) or set(value) != set(default):
            fail(f"a mapping of {', '.join(default)}")
        for k, v in default.items():  # a case's own keys (payload_g) have their own range
            _check_value(k if k in BOUNDS else key, value[k], v, f"{where}.{k}")


def arm_lengths(robot: RobotDescription) -> kinematics.ArmLengths:
    kin = robot.kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(
            f"robot {robot.name!r} is not an anthropomorphic arm (Experiment 1 needs the VSL arm)"
        )
    return kin.arm()


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
                        {"experiment": "experiment1", **cell},
                    )
                )
    return plans


# Experiment 2's command modes (see acquisition.plans.compensation); "history": a history-aware inverse model
COMMANDS = ("ik", "static", "hybrid", "history")


def experiment2(vsl: RobotDescription, rigid: RobotDescription | None, params: dict) -> list[Plan]:
    """Seed 000's Experiment 2: the curve at each (payload, pressure) case, commanded by the model-based IK
    (``ik``), the grey-box static compensation (``static``, ours), the hybrid inverse network (``hybrid``) and
    a history-aware inverse model (``history``, issue 19);
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
        parameters = {"experiment": "experiment2", "commands": mode, **cell}
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
    positions by the rigid IK (elbow up); pressures uniform in the range, payloads from the list. A repeat of
    the campaign visits each bench's points again from another history (``pipeline.floor`` compares the two):
    ``visit_order: shuffled`` in a random order of their own (:func:`visit_order`), ``reversed`` backwards
    (creep then runs the other way along the bench, so the two visits' errors are anti-correlated)."""
    rng = np.random.default_rng(seed)
    n = int(params["points"])
    lo, hi = (np.asarray(params["workspace_mm"][k], float) * MM for k in ("min", "max"))
    targets = rng.uniform(lo, hi, size=(n, 3))
    q = kinematics.vsl_ik(targets, arm_lengths(robot), 1)
    p_lo, p_hi = (v * BAR for v in params["pressure_bar"])
    pressure = rng.uniform(p_lo, p_hi, size=n)
    payload = rng.choice(np.asarray(params["payloads_g"], float) * GRAM, size=n)
    order = params["visit_order"]
    plans = []
    for k, idx in enumerate(np.array_split(np.arange(n), min(benches, n))):
        idx = visit_order(idx, order, seed, k)
        name = f"campaign/{order + '/' if order in REPEATS else ''}bench{k:03d}"  # a repeat's sessions apart
        b = _builder(name, robot, {"experiment": "campaign", "seed": seed, "points": len(idx)})
        previous = q[idx[0]]
        for point in idx:
            speed = together(q[point] - previous, params["move_speed_rad_s"])
            b.pressure(pressure[point]).payload(payload[point]).goto(q[point], speed)
            # the joints travel at the move speed first; settling starts when they arrive
            b.wait(float(np.abs(q[point] - previous).max()) / params["move_speed_rad_s"])
            b.settle(params["settle_s"], index=int(point), hold_s=params["hold_s"])
            previous = q[point]
        plans.append(b.build())
    return plans


SLOWEST = 0.05  # of the move speed: no drive slower (a Dynamixel's profile velocity has 0.024 rad/s steps)


def together(step: np.ndarray, speed: float) -> np.ndarray:
    """Per-joint profile speeds that bring every joint to its goal at once (the largest ``step`` at
    ``speed``): the tip then sweeps the straight joint-space line between two points, which stays near
    them, instead of each drive arriving in turn (a corner up to 60 mm below both, out of the safety box)."""
    largest = float(np.abs(step).max())
    share = np.abs(step) / largest if largest > 0 else np.ones(np.shape(step))  # no move: any speed will do
    return speed * np.maximum(share, SLOWEST)


def visit_order(points: np.ndarray, order: str, seed: int, bench: int) -> np.ndarray:
    """One bench's ``points`` in the order it visits them: as drawn, backwards, or shuffled from the
    bench's own seed (``seed``, :data:`SHUFFLE_STREAM`, ``bench``; never the drawn order itself)."""
    if order == "reversed":
        return points[::-1]
    if order != "shuffled" or len(points) < 2:
        return points
    rng = np.random.default_rng((seed, SHUFFLE_STREAM, bench))
    while True:  # a permutation equal to the drawn order would repeat every history: draw again
        shuffled = rng.permutation(points)
        if not np.array_equal(shuffled, points):
            return shuffled


def expand_experiment(
    experiment: str | Path, overrides: dict | None = None, benches: int = 1, seed: int = 0
) -> tuple[dict[str, RobotDescription], list[Plan], dict]:
    """An experiment's robots (by name, as set up for it), its plans and its parameters (with overrides).
    ``benches``: how many parallel benches the campaign's points are dealt to."""
    from acquisition.plans import popup_experiments
    from models.robot import load_robot

    params = load_experiment(experiment, **(overrides or {}))
    kind = Path(experiment).stem
    known = ["experiment1", "experiment2", "campaign", *popup_experiments.EXPERIMENTS]
    if kind not in known:
        names = ", ".join(f"{k}.yaml" for k in known)
        raise ExperimentError(
            f"no plans for experiment {str(experiment)!r}: an experiment file is named after the "
            f"experiment it sets ({names})"
        )
    source = _shown(_experiment_path(experiment))
    check_experiment(kind, params, source, overridden=set(overrides or ()))
    check_size(kind, params, source, overridden=set(overrides or ()))
    # robots by their names, as plans name them: ``robot`` may be a description's path
    arm = load_robot(params["robot"])
    robots = {arm.name: arm}
    if kind in ("experiment1", "experiment2"):
        rigid = load_robot(params["rigid_robot"]) if params["rigid_arm"] else None
        if rigid is not None and robots.setdefault(rigid.name, rigid) is not rigid:
            raise ExperimentError(f"{source}: robot and rigid_robot are both named {rigid.name!r}: the plans "
                                  "tell their arms apart by name")  # fmt: skip
        expand = experiment1 if kind == "experiment1" else experiment2
        plans = expand(arm, rigid, params)
    elif kind == "campaign":
        plans = campaign(arm, params, benches=benches, seed=seed)
    elif kind in popup_experiments.EXPERIMENTS:
        links = [link.name for link in arm.links]
        if "link" in params and params["link"] not in links:
            where = "--set link" if "link" in (overrides or {}) else f"{source}: link"
            raise ExperimentError(f"{where}: {params['link']!r}: robot {params['robot']!r} has no such link "
                                f"(its links: {', '.join(links)})")  # fmt: skip
        robot = popup_experiments.bench_robot(arm, params)
        robots = {robot.name: robot}
        plans = popup_experiments.EXPERIMENTS[kind](robot, params)
    check_plans(plans, "--set" if overrides else source)
    return robots, plans, params


def _experiment_path(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    return path if path.suffix else EXPERIMENT_DIR / f"{name_or_path}.yaml"
