"""The experiment files of ``configs/experiments/`` as pydantic models, one per experiment kind: what
``vslab schema experiment`` turns into JSON Schemas so that editors complete and check those files.

An experiment file is named after the experiment it sets (``campaign.yaml``, ``popup_reach.yaml``, …) and
gives every parameter of that experiment. Each parameter's type and range come from the same tables
:func:`acquisition.plans.experiments.check_experiment` applies (``COUNTS``, ``BOUNDS``, ``POSITIVE``, …),
by the kind of its shipped value, so the models and the loader refuse the same values. Each field's
description gives the unit; its schema ``default`` is the shipped file's value. All parameters are required
(the loader needs every one).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from acquisition.plans import experiments as ex
from models.trajectories import EXPERIMENT1_NAMES
from models.units import unit_of_name


class ExperimentFile(BaseModel):
    """Base of every experiment kind's file: unknown keys refused, no type coercion (``"1"`` is no number)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


ROBOT = "a name in configs/robots/ or the path of a robot description's YAML file"
# Text parameters with a fixed set of values beyond the loader's CHOICES: refused when the plans are built
NAMED = {"trajectory": EXPERIMENT1_NAMES, "trajectories": EXPERIMENT1_NAMES, "commands": ex.COMMANDS}

# Each kind's parameters: key → description with its unit. The shipped file's value (configs/experiments/)
# gives the parameter's kind (true/false, integer count, number, text, list, mapping), as it does for the
# loader, and is the schema's ``default``: read from the file, never copied here.
# The set-up both POPUP link tests share (a link clamped as a cantilever), then each test's own parameters
LINK_TEST = {
    "robot": f"The arm: {ROBOT}.",
    "without_masses": "Masses of the description taken off for the test (names).",
    "rigid_links": "Links made rigid for the test (names): × 1000 stiffer, no hysteresis.",
    "fixed_joints": "Drives × 1000 stiffer, without backlash (the link on a fixed joint).",
    "pose_deg": "Joint angles during the test (°), one per actuated joint.",
    "pressures_kpa": "Link pressures tested (kPa).",
}
PARAMETERS: dict[str, dict[str, str]] = {
    "campaign": {
        "robot": f"The arm: {ROBOT}.",
        "points": "Settled static points drawn (SEED: n of the paper's data set).",
        "pressure_bar": "Link pressure range [low, high] (bar), drawn uniformly.",
        "payloads_g": "Payloads (g), one chosen uniformly per point.",
        "workspace_mm": "Box of tip targets in the base frame (mm): its min and max corners [x, y, z].",
        "move_speed_rad_s": "Joint speed between points (rad/s).",
        "settle_s": "Wait for links and pressures at rest at each point (s).",
        "hold_s": "Averaging window of one static point (s).",
        "visit_order": (
            "Order the points are visited in: as drawn; shuffled (the same points in another random order); "
            "reversed."
        ),
    },
    "experiment1": {
        "robot": f"The VSL arm: {ROBOT}.",
        "rigid_robot": f"The rigid-link arm: {ROBOT}.",
        "trajectories": "Trajectories followed (SEED: Fig. 5).",
        "payloads_g": "Payloads (g).",
        "pressures_bar": "VSL link pressures (bar).",
        "rigid_arm": "Also follow the trajectories on the rigid-link arm.",
        "repetitions": "Runs of each trajectory (mean ± std over them).",
        "speed_m_s": "End-effector speed along the trajectory (m/s).",
        "points_per_segment": "Set-points per straight line or arc.",
        "settle_s": "Wait after a pressure or payload change, before the first run (s).",
        "return_speed_rad_s": "Joint speed back to the start between repetitions (rad/s).",
        "rest_s": "Pause at the start point between repetitions (s).",
    },
    "experiment2": {
        "robot": f"The VSL arm: {ROBOT}.",
        "rigid_robot": f"The rigid-link arm: {ROBOT}.",
        "trajectory": "The trajectory followed (SEED: Figs. 6–7).",
        "cases": "The (payload in g, link pressure in bar) cases the trajectory is followed at.",
        "commands": (
            "Command modes: ik (model-based IK), static (grey-box compensation), hybrid (the inverse "
            "network, needs a trained model), history (a history-aware inverse model)."
        ),
        "rigid_arm": "Also follow the trajectory on the rigid-link arm, with the model-based IK.",
        "repetitions": "Runs of each case and command mode.",
        "speed_m_s": "End-effector speed along the trajectory (m/s).",
        "points_per_segment": "Set-points per straight line or arc.",
        "settle_s": "Wait after a pressure or payload change, before the first run (s).",
        "return_speed_rad_s": "Joint speed back to the start between repetitions (rad/s).",
        "rest_s": "Pause at the start point between repetitions (s).",
    },
    "popup_deploy": {
        "robot": f"The arm: {ROBOT}.",
        "pose_deg": "Joint angles while the arm deploys (°), one per actuated joint.",
        "set_points_kpa": "Inflation pressure of each link (kPa), by pressure channel.",
        "order": "Pressure channels in the order they are inflated.",
        "fill_time_constants": "Wait per link: dead time + this many regulator time constants.",
        "deflated_s": "Recording of the deflated arm before inflating (s).",
        "hold_s": "Hold of the deployed arm, one static point (s).",
    },
    "popup_impact": {
        **LINK_TEST,
        "taps": "Hammer taps per pressure.",
        "tap_impulse_nms": "Angular impulse of one tap about the tapped joint (N·m·s).",
        "settle_s": "Wait for pressure and link at rest before the first tap (s).",
        "record_s": "Recording of the free oscillation after each tap (s).",
    },
    "popup_reach": {
        "robot": f"The arm: {ROBOT}.",
        "pressure_kpa": "Pressure of both links (kPa).",
        "payload_kg": "Payload at the tip (kg).",
        "allow_wrinkling": "Let a link's moment pass M_w (held below the collapse limit instead).",
        "q0_deg": "Start pose (°), one angle per actuated joint.",
        "target_mm": "Target of the tip in the base frame [x, y, z] (mm).",
        "v0_m_s": "Top tip speed of the velocity law (m/s).",
        "a0_m_s2": "Tip acceleration of the velocity law (m/s²).",
        "dt_s": "Period of the joint set-points (s).",
        "tolerance_mm": "The planned (rigid) tip stops within this distance of the target (mm).",
        "settle_s": "Wait for links at pressure and the arm still (s).",
        "hold_s": "Settled holds at the start and at the target (s).",
    },
    "popup_static": {
        **LINK_TEST,
        "link": "The link under test (a link of the robot): its moment sets the loads.",
        "load_steps": "Load increments from no mass up to the largest load.",
        "max_collapse_fraction": "Largest load as a fraction of the collapse moment M_c(p).",
        "repetitions": "Loading-unloading cycles averaged at each pressure.",
        "pressure_settle_s": "Wait for pressure and link at rest before the first load (s).",
        "settle_s": "Wait after each load change (s).",
        "hold_s": "Settled hold averaged into one static point (s).",
        "allow_wrinkling": "Let the link's moment pass M_w (safety still stops at the collapse limit).",
    },
    "popup_survey": {
        "robot": f"The arm: {ROBOT}.",
        "points": "Settled poses drawn.",
        "pressure_kpa": "Link pressure range [low, high] (kPa), drawn uniformly.",
        "payloads_g": "Payloads (g), one chosen uniformly per pose.",
        "joints_deg": (
            "Box of joint angles (°) drawn uniformly: its min and max corners; refused poses are drawn again."
        ),
        "move_speed_rad_s": "Joint speed between points (rad/s).",
        "settle_s": "Wait for links and pressures at rest at each point (s).",
        "hold_s": "Averaging window of one static point (s).",
    },
}
TITLES = {
    "campaign": "Seed 000's data campaign: random pressure, joint position and payload per settled point.",
    "experiment1": "Seed 000's Experiment 1: trajectories × payloads × VSL pressures and the rigid arm.",
    "experiment2": "Seed 000's Experiment 2: the curve with model-based and with compensated commands.",
    "popup_deploy": "Seed 001's deployment: link 1 inflated, then link 2 once link 1 reads its set point.",
    "popup_impact": "Seed 001's dynamic link test: hammer taps on link 2 at each pressure.",
    "popup_reach": "Seed 001's target reaching with the velocity law (eq. 3).",
    "popup_static": "Seed 001's static link test: tip loads on link 2 as a cantilever at each pressure.",
    "popup_survey": "POPUP's static survey: settled poses spread over the workspace.",
}


def _number(key: str, integer: bool) -> Any:
    """The type of numeric parameter ``key``: the checks ``experiments._check_value`` applies to it."""
    low, high = ex.BOUNDS.get(
        key, (-math.inf, ex.MAX_WAIT_S) if key.endswith("_s") else (-math.inf, math.inf)
    )
    if integer:
        least = max(low, 1 if key in ex.COUNTS else 0)
        return Annotated[int, Field(ge=least, **({"le": high} if high < math.inf else {}))]
    if key not in ex.SIGNED:
        low = max(low, 0.0)
    bounds: dict[str, float] = {"gt": 0.0} if key in ex.POSITIVE and low <= 0 else {}
    if not bounds and low > -math.inf:
        bounds["ge"] = low
    if high < math.inf:
        bounds["le"] = high
    return Annotated[float, Field(**bounds)]


def _type(key: str, default: Any, name: str) -> Any:
    """The type of parameter ``key`` whose shipped value is ``default`` (recursively into lists, mappings)."""
    if isinstance(default, bool):
        return bool
    if isinstance(default, int | float):
        return _number(key, integer=key in ex.COUNTS or key in ex.INDICES)
    if isinstance(default, str):
        choices = ex.CHOICES.get(key) or NAMED.get(key)
        return Literal[choices] if choices else Annotated[str, Field(min_length=1)]
    if isinstance(default, list):
        fixed = key in ex.FIXED_LENGTH
        least = len(default) if fixed else 0 if key in ex.MAY_BE_EMPTY else 1
        most = len(default) if fixed else ex.MAX_LIST_ITEMS
        return Annotated[list[_type(key, default[0], name)], Field(min_length=least, max_length=most)]
    if isinstance(default, dict):  # a mapping of exactly these keys (a box's min/max, a case)
        fields = {k: (_type(k if k in ex.BOUNDS else key, v, name), ...) for k, v in default.items()}
        model = f"{name}{''.join(part.title() for part in key.split('_'))}"
        return create_model(model, __base__=ExperimentFile, __doc__=f"An item of {key}.", **fields)
    raise TypeError(f"{key}: no parameter type for {default!r}")


def _extra(key: str, default: Any) -> dict[str, Any]:
    """A parameter's schema annotations beyond its type: its shipped value as ``default``, its ``unit``."""
    return {"default": default} | ({"unit": u} if (u := unit_of_name(key)) else {})


def _model(kind: str) -> type[ExperimentFile]:
    """The model of experiment ``kind``'s file: every parameter required, its shipped value as the schema's
    ``default``."""
    name = "".join(part.title() for part in kind.split("_"))
    shipped = ex.load_experiment(kind)
    if missing := sorted(set(shipped) - set(PARAMETERS[kind])):
        raise KeyError(f"{kind}: no description of {missing} in PARAMETERS (experiment_files.py)")
    fields = {
        key: (
            _type(key, shipped[key], name),
            Field(description=text, json_schema_extra=_extra(key, shipped[key])),
        )
        for key, text in PARAMETERS[kind].items()
    }
    return create_model(name, __base__=ExperimentFile, __doc__=TITLES[kind], **fields)


# experiment kind (its file's name) → the model of its file
EXPERIMENT_FILES: dict[str, type[ExperimentFile]] = {kind: _model(kind) for kind in PARAMETERS}
