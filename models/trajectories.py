"""Timed set-points: Algorithms 1–2 and Experiment 1's trajectories of seed 000, the velocity law of seed 001
(eq. 3) and its target reaching.

A plan is a ``SetPoints``: times t (N,), Cartesian targets x (N, 3), joint set-points q from the IK (N, 3)
and joint velocities q̇ = J⁻¹(q) ẋ (N, 3), which the paper's Move(q, q̇) sends as profile velocities.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.kinematics import ArmLengths, inverse_jacobian_velocity, vsl_ik, vsl_jacobian

Array = NDArray[np.float64]

# seed 000, section V.A (mm, y = 0)
EXPERIMENT1_POINTS_MM = {
    "linear": {"x0": (300, 0, 50), "xg": (300, 0, 350)},
    "curve": {
        "arcs": (
            {"x0": (300, 0, 50), "xg": (400, 0, 150), "xc": (300, 0, 150)},
            {"x0": (400, 0, 150), "xg": (300, 0, 50), "xc": (400, 0, 50)},
        )
    },
    "square": {"corners": ((350, 0, 50), (250, 0, 50), (250, 0, 150), (350, 0, 150))},
}
EXPERIMENT1_NAMES = tuple(EXPERIMENT1_POINTS_MM)


@dataclass(frozen=True)
class SetPoints:
    """Timed set-points of one trajectory (SI units)."""

    t: Array
    x: Array
    q: Array
    qd: Array

    def __len__(self) -> int:
        return len(self.t)

    def concat(self, other: SetPoints) -> SetPoints:
        """``other`` appended, its clock continuing one of its own first steps after self's last point."""
        first_step = other.t[1] - other.t[0] if len(other) > 1 else 0.0
        shift = self.t[-1] + first_step - other.t[0]
        return SetPoints(
            np.concatenate([self.t, other.t + shift]),
            np.concatenate([self.x, other.x]),
            np.concatenate([self.q, other.q]),
            np.concatenate([self.qd, other.qd]),
        )


def _plan(t: Array, x: Array, xdot: Array, lengths: ArmLengths, elbow: int) -> SetPoints:
    q = vsl_ik(x, lengths, elbow)
    qd = inverse_jacobian_velocity(vsl_jacobian(q, lengths), xdot)
    return SetPoints(t, x, q, qd)


def linear(
    x0: ArrayLike, xg: ArrayLike, speed: float, n: int, lengths: ArmLengths, elbow: int = 1
) -> SetPoints:
    """Algorithm 1: N equal steps from x0 to xg at constant Cartesian speed (N + 1 points, x0 first)."""
    x0, xg = np.asarray(x0, float), np.asarray(xg, float)
    length = np.linalg.norm(xg - x0)
    if length == 0 or speed <= 0 or n < 1:
        raise ValueError("a linear trajectory needs distinct end points, speed > 0 and n ≥ 1")
    s = np.arange(n + 1) / n
    x = x0 + s[:, None] * (xg - x0)
    xdot = np.broadcast_to(speed * (xg - x0) / length, x.shape)
    return _plan(s * length / speed, x, xdot, lengths, elbow)


def _arc_angle(x: Array, xc: Array) -> float:
    """Angle φ of x on a circle about xc in the XZ plane, with x = xc + r [sin φ, 0, −cos φ]."""
    return float(np.arctan2(x[0] - xc[0], -(x[2] - xc[2])))


def circular(
    x0: ArrayLike, xg: ArrayLike, xc: ArrayLike, speed: float, n: int, lengths: ArmLengths, elbow: int = 1
) -> SetPoints:
    """Algorithm 2 generalised: the shorter arc about xc from x0 to xg in the XZ plane, N steps.

    The paper's loop x_{k+1} = [xc1 + r sin(αk), 0, xc3 − r cos(αk)], α = π/(2N), is the case of x0 directly
    below xc and a quarter turn; here the start and end angles come from x0 and xg (an exact half turn goes
    the way of increasing φ). N + 1 points, x0 first; ẋ is tangent with magnitude ``speed``.
    """
    x0, xg, xc = (np.asarray(v, float) for v in (x0, xg, xc))
    r0, rg = np.linalg.norm(x0 - xc), np.linalg.norm(xg - xc)
    if abs(r0 - rg) > 1e-6:
        raise ValueError(
            f"x0 and xg are not on one circle about xc (radii {r0 * 1e3:.3f} and {rg * 1e3:.3f} mm)"
        )
    if np.any(np.abs([x0[1], xg[1], xc[1]]) > 1e-12):
        raise ValueError("circular trajectories lie in the XZ plane: y must be 0")
    if r0 == 0 or np.linalg.norm(xg - x0) == 0 or speed <= 0 or n < 1:
        raise ValueError("a circular trajectory needs x0 ≠ xc, x0 ≠ xg, speed > 0 and n ≥ 1")
    phi0 = _arc_angle(x0, xc)
    sweep = _arc_angle(xg, xc) - phi0
    # the shorter way, sweep in (−π, π]; wrap only when needed so that the paper's case stays bit-exact
    if sweep > np.pi:
        sweep -= 2 * np.pi
    elif sweep <= -np.pi:
        sweep += 2 * np.pi
    phi = phi0 + (sweep / n) * np.arange(n + 1)  # as Algorithm 2: α k with α = sweep / N
    x = np.stack([xc[0] + r0 * np.sin(phi), np.zeros_like(phi), xc[2] - r0 * np.cos(phi)], -1)
    direction = np.sign(sweep)
    xdot = speed * direction * np.stack([np.cos(phi), np.zeros_like(phi), np.sin(phi)], -1)
    t = np.abs(phi - phi0) * r0 / speed
    return _plan(t, x, xdot, lengths, elbow)


def experiment1(
    name: str, lengths: ArmLengths, speed: float = 0.02, n_per_segment: int = 50, elbow: int = 1
) -> SetPoints:
    """An Experiment 1 trajectory ('linear', 'curve' or 'square') with the paper's points (seed 000, V.A).

    'curve' is the two arcs, ending back at its start; 'square' is closed (the paper's four points, four
    sides, back to [350, 0, 50] mm). Segments are joined without repeating their shared end points.
    """
    if name not in EXPERIMENT1_POINTS_MM:
        raise ValueError(
            f"unknown Experiment 1 trajectory {name!r}; choose one of {', '.join(EXPERIMENT1_NAMES)}"
        )
    spec = EXPERIMENT1_POINTS_MM[name]
    mm = 1e-3
    if name == "linear":
        return linear(
            np.multiply(spec["x0"], mm), np.multiply(spec["xg"], mm), speed, n_per_segment, lengths, elbow
        )
    if name == "curve":
        arcs = [
            circular(
                np.multiply(a["x0"], mm),
                np.multiply(a["xg"], mm),
                np.multiply(a["xc"], mm),
                speed,
                n_per_segment,
                lengths,
                elbow,
            )
            for a in spec["arcs"]
        ]
        return _join(arcs)
    corners = np.asarray(spec["corners"], float) * mm
    sides = [
        linear(corners[i], corners[(i + 1) % 4], speed, n_per_segment, lengths, elbow) for i in range(4)
    ]  # closed: four sides back to the first corner
    return _join(sides)


def _join(parts: list[SetPoints]) -> SetPoints:
    """Concatenate segments, dropping each later segment's first point (it repeats the previous end)."""
    out = parts[0]
    for part in parts[1:]:
        tail = SetPoints(part.t[1:], part.x[1:], part.q[1:], part.qd[1:])
        shift = out.t[-1] - part.t[0]
        out = SetPoints(
            np.concatenate([out.t, tail.t + shift]),
            np.concatenate([out.x, tail.x]),
            np.concatenate([out.q, tail.q]),
            np.concatenate([out.qd, tail.qd]),
        )
    return out


def velocity_law(d: ArrayLike, t: ArrayLike, v0: float, a0: float) -> Array:
    """Seed 001 eq. (3): v = min(a0 t, v0, √(2 a0 |d|)) · d/|d| (zero at |d| = 0)."""
    d = np.asarray(d, dtype=float)
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    speed = np.minimum(np.minimum(a0 * np.asarray(t, dtype=float)[..., None], v0), np.sqrt(2 * a0 * dist))
    return np.divide(speed * d, dist, out=np.zeros_like(d), where=dist > 0)


def velocity_law_reach(
    chain,
    q0: ArrayLike,
    target: ArrayLike,
    v0: float,
    a0: float,
    dt: float = 0.02,
    tol_m: float = 1e-3,
    max_s: float = 60.0,
    tip: Callable[[Array], Array] | None = None,
) -> tuple[Array, Array]:
    """Seed 001's target reaching (Figs. 12–16): joint angles (times (n,), q (n, A)) every ``dt`` from ``q0``
    until the tip is within ``tol_m`` of ``target`` (m) or ``max_s`` passed. At each step the tip moves with
    eq. (3)'s velocity towards the target, mapped to joint rates by the pseudo-inverse of ``chain``'s rigid
    Jacobian. ``tip(q)`` is where the error is measured: the rigid tip by default (the arm controlled as
    rigid), the soft arm's for visual servoing."""
    tip = tip or chain.position
    target = np.asarray(target, float)
    q = np.asarray(q0, float).copy()
    ts, qs = [0.0], [q.copy()]
    t = 0.0
    while t < max_s:
        d = target - tip(q)
        if np.linalg.norm(d) < tol_m:
            break
        q = q + np.linalg.pinv(chain.jacobian(q)) @ velocity_law(d, t, v0, a0) * dt
        t += dt
        ts.append(t)
        qs.append(q.copy())
    return np.asarray(ts), np.asarray(qs)


def distance_to_path(points: ArrayLike, path: ArrayLike, chunk: int = 4096) -> Array:
    """(n,) distance from each point (n, 3) to the polyline ``path`` (m, 3): the minimum over its segments
    of the point-to-segment distance (seed 000's path error: measured point to the desired path).

    Only the segments that can be nearest are measured (a point is no nearer to the path than to its nearest
    vertex, and a segment within that distance has its middle within it plus half the segment's length), the
    same products for each (point, segment) as measuring every segment: the same distances, bit for bit, in
    a fraction of the time (258k points of Experiment 1 against an 801-vertex path: 13.9 s measuring all)."""
    from scipy.spatial import cKDTree

    p = np.atleast_2d(np.asarray(points, dtype=float))
    vertices = np.asarray(path, dtype=float)
    a, seg = vertices[:-1], vertices[1:] - vertices[:-1]
    length2 = np.maximum((seg**2).sum(axis=1), 1e-300)
    middles = cKDTree(a + seg / 2)
    half = float(np.sqrt(length2).max()) / 2
    bound, _ = cKDTree(vertices).query(p)
    out = np.empty(len(p))
    for start in range(0, len(p), chunk):  # bounded memory: a chunk's candidate pairs at a time
        stop = min(start + chunk, len(p))
        reach = (bound[start:stop] + half) * (1 + 1e-9) + 1e-12  # rounding: never leave the nearest out
        near = middles.query_ball_point(p[start:stop], reach, return_sorted=False)
        counts = np.fromiter(map(len, near), dtype=np.intp, count=len(near))
        j = np.fromiter(itertools.chain.from_iterable(near), dtype=np.intp, count=int(counts.sum()))
        i = np.repeat(np.arange(start, stop), counts)
        rel = p[i] - a[j]
        s = np.clip((rel * seg[j]).sum(axis=1) / length2[j], 0.0, 1.0)
        d = np.sqrt(((rel - s[:, None] * seg[j]) ** 2).sum(axis=1))
        out[start:stop] = np.minimum.reduceat(d, np.cumsum(counts) - counts)
    return out
