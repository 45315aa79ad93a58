"""The matrix D of seed 000 (IV): measured tip x, link pressures p, joint currents i, joint angles q, plus the
model-based columns the hybrid networks take (the rigid FK of q, the rigid IK of x), ids and splits.

Columns (SI): ``x_0..2`` (m, base frame), ``p_<c>`` (Pa, one per link channel), ``i_<k>`` (A, one per servo;
``tau_<k>`` in N·m instead for CiA 402 drives, which report torque),
``q_<j>`` (rad, every actuated joint in the robot's order, measured by the encoders), ``qc_<j>`` (rad, the
commanded joint angles: the servo goals in force, which the servos reach only up to their droop under load —
the inverse model's target), ``fk_0..2`` (m), ``ik_<j>`` (rad; NaN where x is out of reach or the robot
has no closed-form IK: POPUP),
``payload_kg``, ``robot``, ``session``, ``plan`` (the plan the session ran, e.g.
``experiment1/curve/vsl-1bar/25g``), ``point`` (static point number or −1), ``repetition`` (−1 for static
points), ``t`` (s since the session's start), ``split_random`` and ``split_group`` ("train" / "val" / "test").

A dataset's version is the hash of its sessions' content hashes, the stage parameters and the code version
(:func:`dataset_version`), so building unchanged inputs again gives the same version and writes nothing; the
lab's store of them is ``pipeline.dataset_store``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from acquisition.devices.kinds import device_of
from models import kinematics
from models.robot import AnthropomorphicKinematics, RobotDescription
from pipeline.cache import digest, stage_version
from pipeline.tables import columns

SPLITS = ("train", "val", "test")
SPLIT_COLUMNS = ("split_random", "split_group")  # the two ways D is dealt into those parts
FRACTIONS = (0.70, 0.15, 0.15)  # seed 000: 70 / 15 / 15


def joint_angles(df: pd.DataFrame, robot: RobotDescription, servo: str = "servo_position") -> np.ndarray:
    """(n, A) joint angles in the robot's joint order from the timeline's stepper and servo columns: the
    measured ones, or (``servo="goal_position"``) the servo goals in force with the stepper's measured angle
    (a stepper lands on its commanded step; NaN where no goal was recorded)."""
    q = np.full((len(df), len(robot.joints)), np.nan)
    steppers = [k for k, j in enumerate(robot.joints) if j.drive == "stepper"]
    joints = device_of(robot, "joints")
    servo_dev = robot.devices[joints] if joints else None
    names = [j.name for j in robot.joints]
    servos = [names.index(n) for n in (servo_dev.ids if servo_dev else {}) if n in names]
    if steppers:
        q[:, steppers] = columns(df, "stepper_position")[:, : len(steppers)]
    if servos:
        try:
            q[:, servos] = columns(df, servo)[:, : len(servos)]
        except KeyError:  # no goals recorded (a passive recording): unknown, not guessed
            q[:, servos] = np.nan
    return q


def assemble(points: pd.DataFrame, robot: RobotDescription) -> pd.DataFrame:
    """D from registered rows (static points or trajectory samples) of one robot: ``x_0..2`` must already be
    in the base frame; ``servo_position``/``stepper_position``, ``servo_current`` (the Dynamixel servos) or
    ``servo_torque`` (CiA 402 drives: ``tau_<k>`` in N·m in place of ``i_<k>``), ``pressure`` columns as the
    timeline names them. The rigid FK is the robot's chain; the rigid IK is the anthropomorphic arm's closed
    form, NaN on a robot without one (POPUP's D-H chain)."""
    q = joint_angles(points, robot)
    x = columns(points, "x")
    out = {f"x_{k}": x[:, k] for k in range(3)}
    pressure = columns(points, "pressure")
    out |= {f"p_{c}": pressure[:, c] for c in range(pressure.shape[1])}
    for column, name in (("servo_current", "i"), ("servo_torque", "tau")):
        if any(c.startswith(column + "_") for c in points.columns):
            effort = columns(points, column)
            out |= {f"{name}_{k}": effort[:, k] for k in range(effort.shape[1])}
    out |= {f"q_{j}": q[:, j] for j in range(q.shape[1])}
    commanded = joint_angles(points, robot, servo="goal_position")
    out |= {f"qc_{j}": commanded[:, j] for j in range(commanded.shape[1])}
    if isinstance(robot.kinematics, AnthropomorphicKinematics):
        kin = robot.kinematics
        lengths = kin.arm()
        fk, ik = kinematics.vsl_fk(q, lengths), kinematics.vsl_ik_where_reachable(x, lengths)
    else:
        fk, ik = robot.chain().position(q), np.full((len(x), q.shape[1]), np.nan)
    out |= {f"fk_{k}": fk[:, k] for k in range(3)}
    out |= {f"ik_{j}": ik[:, j] for j in range(ik.shape[1])}
    n = len(points)
    out["payload_kg"] = points["payload_kg"].to_numpy(float) if "payload_kg" in points else np.zeros(n)
    out["robot"] = np.full(n, robot.name)
    for name, default in (("session", ""), ("plan", ""), ("point", -1), ("repetition", -1), ("t", np.nan)):
        out[name] = points[name].to_numpy() if name in points else np.full(n, default)
    return pd.DataFrame(out)


def move_rows(rows: pd.DataFrame, robot: RobotDescription) -> pd.DataFrame:
    """A dataset's ``moves`` from registered timeline rows of the moves into its points
    (``pipeline.segment.move_windows``): the tip ``x_*`` (base frame), the encoders ``q_*``, the pressures
    ``p_*``, ``session``, ``point``, ``t`` and ``t_command`` (when the move's goal was sent). D's other
    columns tell nothing of a move (its model columns cost the build a third more time and memory)."""
    x, q, pressure = columns(rows, "x"), joint_angles(rows, robot), columns(rows, "pressure")
    out = {f"x_{k}": x[:, k] for k in range(3)}
    out |= {f"q_{j}": q[:, j] for j in range(q.shape[1])}
    out |= {f"p_{c}": pressure[:, c] for c in range(pressure.shape[1])}
    out |= {name: rows[name].to_numpy() for name in ("session", "point", "t", "t_command")}
    return pd.DataFrame(out)


def add_splits(d: pd.DataFrame, seed: int = 0, group: str = "session") -> pd.DataFrame:
    """``split_random``: rows dealt 70/15/15 at random (the paper's split); ``split_group``: whole groups
    (sessions, or repetitions where there is one session) dealt so that no group spans two splits."""
    rng = np.random.default_rng(seed)
    out = d.copy()
    labels = np.empty(len(d), dtype=object)
    bounds = np.round(np.cumsum(FRACTIONS) * len(d)).astype(int)
    for name, idx in zip(SPLITS, np.split(rng.permutation(len(d)), bounds[:-1]), strict=True):
        labels[idx] = name
    out["split_random"] = labels
    keys = d[group].astype(str)
    if keys.nunique() < 3 and "repetition" in d:
        keys = keys + "/" + d["repetition"].astype(str) + "/" + d["point"].astype(str)
    groups = np.asarray(keys.unique(), dtype=object)
    rng.shuffle(groups)
    sizes = keys.value_counts().reindex(groups).to_numpy()
    ends = np.cumsum(sizes) / len(d)
    which = np.searchsorted(np.cumsum(FRACTIONS)[:-1], ends - sizes / len(d) / 2)  # by each group's middle
    out["split_group"] = keys.map(dict(zip(groups, np.array(SPLITS)[which], strict=True))).to_numpy()
    return out


def dataset_version(made_from: dict[str, str], parameters: dict) -> str:
    """The version id: a hash of its sessions' content hashes (``made_from``), the parameters and the code
    version."""
    inputs = {"made_from": dict(sorted(made_from.items())), "parameters": parameters}
    return digest(inputs | {"code": stage_version("dataset")})[:16]
