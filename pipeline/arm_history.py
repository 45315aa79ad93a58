"""What a settled point of the VSL arm depends on beyond its own joints, pressures and payload: the loads
along the moves that led to it and the hysteresis state they leave in each link (``pipeline.twin_fit``
follows each session's points through them), and which masses each bending link carries.

The loads are the rigid arm's gravity moments about the links' hinges along straight joint-space moves
between consecutive points, in parts linear in what the fit scales (the payload's, each link's carried
masses'), so a fit scales them without recomputing the moments.
"""

from __future__ import annotations

import numba
import numpy as np

from models.prbm import bouc_wen_step
from models.robot import TIP_FRAME, RobotDescription
from models.statics import gravity_moments


def mass_bodies(robot: RobotDescription, links) -> dict[str, list[str]]:
    """The point masses each bending link carries on the body after its hinge, up to the next link's (the
    tool point's on the last): {link: [mass names]}."""
    rows = [row.joint for row in robot.dh_rows()]
    hinges = [(rows.index(link.virtual_joints[0]), link.name) for link in links]
    out: dict[str, list[str]] = {}
    for mass in robot.masses:
        at = len(rows) - 1 if mass.frame == TIP_FRAME else rows.index(mass.frame)
        carriers = [name for row, name in hinges if row <= at]
        if carriers:
            out.setdefault(carriers[-1], []).append(mass.name)
    return out


def scaled_masses(robot: RobotDescription, links, values: dict) -> list:
    """The description's point masses, each link's body's scaled by ``<link>.mass_scale`` in ``values``."""
    scale = {m: values.get(f"{body}.mass_scale", 1.0) for body, names in mass_bodies(robot, links).items()
             for m in names}  # fmt: skip
    return [
        mass.model_copy(update={"mass_kg": mass.mass_kg * scale.get(mass.name, 1.0)}) for mass in robot.masses
    ]


def session_order(sessions: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(sessions, longest) row indices of each session's points in time order, padded with −1."""
    groups = [np.flatnonzero(sessions == s) for s in np.unique(sessions)]
    order = np.full((len(groups), max(len(g) for g in groups)), -1)
    for k, g in enumerate(groups):
        order[k, : len(g)] = g[np.argsort(t[g], kind="stable")]
    return order


def path_parts(robot: RobotDescription, links, q: np.ndarray, m: np.ndarray, order: np.ndarray,
                substeps: int, moves: tuple | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """(n, substeps, links) the links' torques along the move into each point from the one before it in its
    session (joint angles interpolated in a straight line, the rigid arm's moments; the point's own last): the
    hysteresis follows the path, which need not be monotone between two points. With ``moves`` (the joint
    angles and bending where each link's load turns along the arm's own move,
    ``pipeline.move_paths.simulated_moves``), at those instead (then ``substeps`` is theirs). In parts, which
    the torque is linear in: the payload's (``payload``), each bending link's body's masses at their nominal
    values (by link name: the fit scales them) and the other masses' (``fixed``)."""
    before = np.arange(len(q))
    for row in order:
        row = row[row >= 0]
        before[row[1:]] = row[:-1]
    virtual = [i for i, r in enumerate(robot.dh_rows()) if not r.joint.startswith("q")]

    def part(masses: list, payload) -> np.ndarray:
        out = np.zeros((len(q), substeps if moves is None else moves[0].shape[1], len(virtual)))
        if not masses and not np.any(payload):
            return out
        arm = robot.model_copy(update={"masses": masses})
        if moves is not None:
            for s in range(moves[0].shape[1]):
                for k, row in enumerate(virtual):
                    out[:, s, k] = gravity_moments(arm, moves[0][:, s, k], moves[1][:, s, k], payload)[:, row]
            return out
        for s in range(1, substeps + 1):
            between = q[before] + (q - q[before]) * (s / substeps)
            out[:, s - 1] = gravity_moments(arm, between, None, payload)[:, virtual]
        return out

    bodies = mass_bodies(robot, links)
    carried = {name for names in bodies.values() for name in names}
    parts = {"payload": part([], m), "fixed": part([x for x in robot.masses if x.name not in carried], 0.0)}
    for body, names in bodies.items():
        parts[body] = part([x for x in robot.masses if x.name in names], 0.0)
    return parts


def path_torques(parts: dict[str, np.ndarray], values: dict) -> np.ndarray:
    """The path's torques (see :func:`path_parts`) with each body's masses scaled as ``values`` say."""
    out = parts["payload"] + parts["fixed"]
    for body, torque in parts.items():
        if body not in ("payload", "fixed"):
            out = out + values.get(f"{body}.mass_scale", 1.0) * torque
    return out


def hysteresis_states(path: np.ndarray, tau_y: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(n, links) Bouc–Wen state of each point: the torques along each session's moves (``path``, see
    :func:`path_torques`) stepped through in time ``order`` (sessions × points, −1 past a session's end)
    from a virgin link (z = 0 at τ = 0), as the twin's links are. Compiled, as the twin's kernel steps its
    links (its ``expm1`` is the C library's, as there: numpy's own differs from it in the last bit of 7 % of
    values): a 600-point fit asks for it ~170 times, 10 ms each in numpy, 0.3 ms here."""
    z = np.zeros((path.shape[0], path.shape[2]))
    _step_sessions(np.ascontiguousarray(path, float), np.asarray(tau_y, float), order.astype(np.int64), z)
    return z


_bouc_wen_step = numba.njit(cache=True, error_model="numpy")(bouc_wen_step)


@numba.njit(cache=True, error_model="numpy")
def _step_sessions(path, tau_y, order, z):
    for s in range(order.shape[0]):
        for link in range(path.shape[2]):
            state, prev = 0.0, 0.0
            for row in order[s]:
                if row < 0:
                    continue
                for sub in range(path.shape[1]):
                    state = _bouc_wen_step(state, path[row, sub, link] - prev, tau_y[link])
                    prev = path[row, sub, link]
                z[row, link] = state


def creep_states(elastic: np.ndarray, t: np.ndarray, order: np.ndarray, time_constant_s: float) -> np.ndarray:
    """(n, links) each point's state of a creep element with time constant ``time_constant_s``, per unit of
    its fraction (``effects.creep``: τᵢ ẋᵢ = aᵢ δ_el − xᵢ): the first-order lag of the links' elastic bending
    ``elastic`` (n, links; τ/k at each point) through each session's points in time ``order``, each point's
    load held from the point before it: x_j = δ_j + (x_{j−1} − δ_j) e^{−(t_j − t_{j−1})/τᵢ}. A session starts
    with its links at rest under its first point's load (held long before it, as the twin starts them)."""
    out = np.zeros_like(elastic)
    _lag_sessions(np.ascontiguousarray(elastic, float), np.asarray(t, float), order.astype(np.int64),
                  float(time_constant_s), out)  # fmt: skip
    return out


@numba.njit(cache=True, error_model="numpy")
def _lag_sessions(elastic, t, order, time_constant, out):
    for s in range(order.shape[0]):
        first = order[s, 0]
        for link in range(elastic.shape[1]):
            state, since = elastic[first, link], t[first]
            for row in order[s]:
                if row < 0:
                    continue
                state = elastic[row, link] + (state - elastic[row, link]) * np.exp(
                    -(t[row] - since) / time_constant
                )
                since = t[row]
                out[row, link] = state
