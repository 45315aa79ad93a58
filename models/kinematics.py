"""Rigid kinematics: the VSL arm of seed 000 (eqs. 1–8) and a D-H chain with virtual joints (seed 001).

Everything is vectorised over leading batch axes (numpy, float64, SI units: m, rad).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.errors import ModelError

Array = NDArray[np.float64]


class UnreachableError(ModelError, ValueError):
    """A Cartesian target lies outside the arm's reachable workspace."""


class SingularityError(ModelError, ValueError):
    """The Jacobian cannot be inverted at this configuration."""


@dataclass(frozen=True)
class ArmLengths:
    """The anthropomorphic arm: link lengths (m), L1 base to J2 axis, L2 J2→J3, L3 J3→end-effector, and each
    joint's offset (rad): its true angle minus the encoder's reading (zero for the papers' arm). The functions
    below take and return encoder angles."""

    l1: float
    l2: float
    l3: float
    offsets: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def true_angles(self, q: ArrayLike) -> Array:
        """The joints' true angles of encoder readings q (..., 3)."""
        q = np.asarray(q, dtype=float)
        return q + np.asarray(self.offsets) if any(self.offsets) else q


# ---------------------------------------------------------------------------------------- VSL arm
def vsl_fk_transform(q: ArrayLike, lengths: ArmLengths) -> Array:
    """⁰T₃ of eq. (1) for joint angles q (..., 3) → (..., 4, 4)."""
    q = lengths.true_angles(q)
    c1, s1 = np.cos(q[..., 0]), np.sin(q[..., 0])
    c2, s2 = np.cos(q[..., 1]), np.sin(q[..., 1])
    c23, s23 = np.cos(q[..., 1] + q[..., 2]), np.sin(q[..., 1] + q[..., 2])
    reach = lengths.l2 * c2 + lengths.l3 * c23
    out = np.zeros((*q.shape[:-1], 4, 4))
    out[..., 0, :] = np.stack([c1 * c23, -c1 * s23, s1, c1 * reach], -1)
    out[..., 1, :] = np.stack([s1 * c23, -s1 * s23, -c1, s1 * reach], -1)
    out[..., 2, :3] = np.stack([s23, c23, np.zeros_like(s23)], -1)
    out[..., 2, 3] = lengths.l1 + lengths.l2 * s2 + lengths.l3 * s23
    out[..., 3, 3] = 1.0
    return out


def vsl_fk(q: ArrayLike, lengths: ArmLengths) -> Array:
    """End-effector position (..., 3) of eq. (1)."""
    q = lengths.true_angles(q)
    c1, s1 = np.cos(q[..., 0]), np.sin(q[..., 0])
    reach = lengths.l2 * np.cos(q[..., 1]) + lengths.l3 * np.cos(q[..., 1] + q[..., 2])
    z = lengths.l1 + lengths.l2 * np.sin(q[..., 1]) + lengths.l3 * np.sin(q[..., 1] + q[..., 2])
    return np.stack([c1 * reach, s1 * reach, z], -1)


def vsl_ik(x: ArrayLike, lengths: ArmLengths, elbow: int = 1) -> Array:
    """Joint angles (..., 3) reaching positions x (..., 3): eqs. (2)–(7), λ = ``elbow`` (+1 up, −1 down).

    θ3 is returned in (−π, π] (before the joint offsets are taken off: the result is the encoders').
    Targets outside the annulus |L2 − L3| ≤ r3 ≤ L2 + L3 raise UnreachableError.
    """
    if elbow not in (1, -1):
        raise ValueError(f"elbow must be +1 (up) or -1 (down), got {elbow!r}")
    x = np.asarray(x, dtype=float)
    l2, l3 = lengths.l2, lengths.l3
    r1 = np.hypot(x[..., 0], x[..., 1])
    r2 = x[..., 2] - lengths.l1
    r3 = np.hypot(r1, r2)
    tol = 1e-12
    bad = ~((r3 <= l2 + l3 + tol) & (r3 >= abs(l2 - l3) - tol))  # NaN targets are unreachable too
    if np.any(bad):
        index = int(np.flatnonzero(bad.reshape(-1))[0])
        first = x.reshape(-1, 3)[index] * 1e3
        raise UnreachableError(
            f"{int(bad.sum())} target(s) unreachable, first at "
            f"[{first[0]:.1f}, {first[1]:.1f}, {first[2]:.1f}] mm (flat index {index}):"
            f" distance from the J2 axis must lie in [{abs(l2 - l3) * 1e3:.1f}, {(l2 + l3) * 1e3:.1f}] mm"
        )
    theta1 = np.arctan2(x[..., 1], x[..., 0])  # r1 = 0 (on the J1 axis): θ1 = 0
    # r3 = 0 (only reachable when L2 = L3): the arm is folded and any θ2 works; cos_a = 0 picks θ2 = λπ/2
    num_a = r3**2 + l2**2 - l3**2
    cos_a = np.clip(np.divide(num_a, 2 * r3 * l2, out=np.zeros_like(r3), where=r3 > 0), -1.0, 1.0)
    cos_b = np.clip((l2**2 + l3**2 - r3**2) / (2 * l2 * l3), -1.0, 1.0)
    theta2 = np.arctan2(r2, r1) + elbow * np.arccos(cos_a)
    theta3 = np.pi + elbow * np.arccos(cos_b)
    theta3 = np.pi - np.mod(np.pi - theta3, 2 * np.pi)  # wrap to (−π, π]
    q = np.stack([theta1, theta2, theta3], -1)
    return q - np.asarray(lengths.offsets) if any(lengths.offsets) else q  # the encoders' readings


def vsl_ik_where_reachable(x: ArrayLike, lengths: ArmLengths, elbow: int = 1) -> Array:
    """:func:`vsl_ik` of every reachable position of x (n, 3), NaN for the others (out of the annulus, or
    NaN themselves): the rigid IK column of a dataset, where a measured tip may lie beyond the rigid arm's
    reach."""
    x = np.asarray(x, dtype=float).reshape(-1, 3)
    out = np.full((len(x), 3), np.nan)
    r3 = np.hypot(np.hypot(x[:, 0], x[:, 1]), x[:, 2] - lengths.l1)
    ok = np.isfinite(r3) & (r3 <= lengths.l2 + lengths.l3) & (r3 >= abs(lengths.l2 - lengths.l3))
    if ok.any():
        out[ok] = vsl_ik(x[ok], lengths, elbow)
    return out


def vsl_jacobian(q: ArrayLike, lengths: ArmLengths) -> Array:
    """∂x/∂q (..., 3, 3) of eq. (1)'s position.

    This is the true derivative: eq. (8) as printed has two errors in its second row (∂y/∂q2 is
    −s1(L2 s2 + L3 s23), not +, and ∂y/∂q3 is −L3 s1 s23, not −L3 s1 c23).
    """
    q = lengths.true_angles(q)
    c1, s1 = np.cos(q[..., 0]), np.sin(q[..., 0])
    c2, s2 = np.cos(q[..., 1]), np.sin(q[..., 1])
    c23, s23 = np.cos(q[..., 1] + q[..., 2]), np.sin(q[..., 1] + q[..., 2])
    l2, l3 = lengths.l2, lengths.l3
    reach = l2 * c2 + l3 * c23
    rise = l2 * s2 + l3 * s23
    zero = np.zeros_like(c1)
    return np.stack(
        [
            np.stack([-s1 * reach, -c1 * rise, -l3 * c1 * s23], -1),
            np.stack([c1 * reach, -s1 * rise, -l3 * s1 * s23], -1),
            np.stack([zero, reach, l3 * c23], -1),
        ],
        -2,
    )


def inverse_jacobian_velocity(jac: ArrayLike, xdot: ArrayLike, max_condition: float = 1e8) -> Array:
    """Joint velocities q̇ solving J q̇ = ẋ for batches; raises SingularityError near a singularity."""
    jac = np.asarray(jac, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.linalg.cond(jac)
    bad = ~(cond <= max_condition)  # inf/NaN count as singular
    if np.any(bad):
        index = int(np.flatnonzero(bad.reshape(-1))[0])
        raise SingularityError(
            f"Jacobian too close to singular at {int(bad.sum())} of {bad.size} configuration(s);"
            f" first at flat index {index} (condition number {cond.reshape(-1)[index]:.3g}"
            f" > {max_condition:.3g})"
        )
    return np.linalg.solve(jac, np.asarray(xdot, dtype=float)[..., None])[..., 0]


# ------------------------------------------------------------------------------------- D-H chains
@dataclass(frozen=True)
class DHRow:
    """Standard D-H row T = Rz(θ) Tz(d) Tx(a) Rx(α) with θ = value of ``joint`` + ``offset``.
    Joints named q* are actuated; any other name is a virtual joint (link bending)."""

    a: float
    alpha: float
    d: float
    joint: str
    offset: float = 0.0

    @property
    def actuated(self) -> bool:
        return self.joint.startswith("q")


# seed 001, Table 2 (a mm, α rad, d mm, θ variable); the OCR's "92"/"93" are q2/q3
POPUP_TABLE2_MM: tuple[tuple[float, float, float, str], ...] = (
    (0.0, np.pi / 2, 152.70, "q1"),
    (94.0, -np.pi / 2, 39.35, "q2"),
    (0.0, np.pi / 2, 0.0, "d11"),
    (634.0, np.pi, 0.0, "d12"),
    (94.0, np.pi / 2, 157.80, "q3"),
    (0.0, -np.pi / 2, 0.0, "d21"),
    (590.0, 0.0, 0.0, "d22"),
)


def dh_chain_from_table(rows_mm: Sequence[tuple[float, float, float, str]]) -> DHChain:
    """A chain from rows given as (a mm, α rad, d mm, joint name)."""
    return DHChain([DHRow(a * 1e-3, alpha, d * 1e-3, joint) for a, alpha, d, joint in rows_mm])


BATCHED_POINTS = 128  # from this many points on, DHChain.frames composes column by column (see there)


def _dh_transforms(a: Array, alpha: Array, d: Array, theta: Array) -> Array:
    """Per-row transforms (..., R, 4, 4) for broadcast row parameters and θ (..., R)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    out = np.zeros((*np.shape(theta), 4, 4))  # filled in place: small stacks cost more than the maths
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2], out[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2], out[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa, ca, d
    out[..., 3, 3] = 1.0
    return out


class DHChain:
    """A serial chain of D-H rows with actuated joints q and virtual joints δ."""

    def __init__(self, rows: Sequence[DHRow]) -> None:
        if not rows:
            raise ValueError("a D-H chain needs at least one row")
        names = [r.joint for r in rows]
        if len(set(names)) != len(names):
            raise ValueError(f"joint names must be unique: {names}")
        self.rows = tuple(rows)
        self._actuated = tuple(r.joint for r in rows if r.actuated)
        self._virtual = tuple(r.joint for r in rows if not r.actuated)
        self._a = np.array([r.a for r in rows])
        self._alpha = np.array([r.alpha for r in rows])
        self._cos_alpha, self._sin_alpha = np.cos(self._alpha), np.sin(self._alpha)
        self._d = np.array([r.d for r in rows])
        self._offset = np.array([r.offset for r in rows])
        self._is_actuated = np.array([r.actuated for r in rows])
        index = np.array(
            [self.actuated.index(r.joint) if r.actuated else self.virtual.index(r.joint) for r in rows]
        )
        # each row's θ read from q (actuated rows) or δ (virtual ones); the other index is any valid one
        self._q_rows = index.clip(max=max(len(self._actuated) - 1, 0))
        self._delta_rows = index.clip(max=max(len(self._virtual) - 1, 0))

    @property
    def actuated(self) -> tuple[str, ...]:
        """Names of the actuated joints (q*), in chain order."""
        return self._actuated

    @property
    def virtual(self) -> tuple[str, ...]:
        """Names of the virtual joints (link bending δ), in chain order."""
        return self._virtual

    def theta(self, q: ArrayLike, delta: ArrayLike | None = None) -> Array:
        """Every row's θ (..., R) from q (..., n_actuated) and δ (..., n_virtual)."""
        q = np.asarray(q, dtype=float)
        if q.ndim == 0 or q.shape[-1] != len(self.actuated):
            raise ValueError(
                f"q has shape {q.shape}, the chain needs (..., {len(self.actuated)}): {self.actuated}"
            )
        if delta is None:
            delta = np.zeros((*q.shape[:-1], len(self.virtual)))
        delta = np.asarray(delta, dtype=float)
        try:
            delta = np.broadcast_to(delta, (*q.shape[:-1], len(self.virtual)))
        except ValueError:
            raise ValueError(
                f"delta has shape {delta.shape}, the chain needs (..., {len(self.virtual)})"
                f" matching q's batch {q.shape[:-1]}: {self.virtual}"
            ) from None
        if not self.virtual:
            return q[..., self._q_rows] + self._offset
        return np.where(self._is_actuated, q[..., self._q_rows], delta[..., self._delta_rows]) + self._offset

    def frames(self, q: ArrayLike, delta: ArrayLike | None = None, a: ArrayLike | None = None) -> Array:
        """Cumulative transforms (..., R + 1, 4, 4): index 0 is the base, i + 1 the frame after row i. ``a``:
        the rows' lengths (..., R) where they are not the chain's (links that lengthen with pressure)."""
        theta = self.theta(q, delta)
        lengths = self._a if a is None else np.asarray(a, dtype=float)
        if theta.size >= BATCHED_POINTS * theta.shape[-1]:
            return self._batched_frames(theta, np.broadcast_to(lengths, theta.shape))
        local = _dh_transforms(lengths, self._alpha, self._d, theta)
        out = np.empty((*local.shape[:-3], local.shape[-3] + 1, 4, 4))
        out[..., 0, :, :] = np.eye(4)
        for i in range(local.shape[-3]):
            out[..., i + 1, :, :] = out[..., i, :, :] @ local[..., i, :, :]
        return out

    def _batched_frames(self, theta: Array, lengths: Array) -> Array:
        """:meth:`frames` of many points, each row's Rz(θ)·Tz(d)·Tx(a)·Rx(α) applied to the frame before it
        column by column (x' = cθ x + sθ y; y' = cα (cθ y − sθ x) + sα z; z' = cα z − sα (cθ y − sθ x);
        p' = p + a x' + d z) over contiguous points: the 4 × 4 products' numbers to a bit or two, in a third
        of their time at 17,568 points (a twin fit's campaign); the products take fewer numpy calls, and less
        time, below ~150 points. A view whose points vary slowest in memory."""
        batch = theta.shape[:-1]
        cos, sin = np.cos(np.moveaxis(theta, -1, 0)), np.sin(np.moveaxis(theta, -1, 0))
        lengths = np.moveaxis(lengths, -1, 0)
        out = np.zeros((theta.shape[-1] + 1, 4, 4, *batch))
        out[:, 3, 3] = 1.0
        out[0, 0, 0] = out[0, 1, 1] = out[0, 2, 2] = 1.0
        x, y, z = out[0, :3, 0], out[0, :3, 1], out[0, :3, 2]
        p = out[0, :3, 3]
        for i, (ca, sa, d) in enumerate(zip(self._cos_alpha, self._sin_alpha, self._d, strict=True)):
            ct, st = cos[i], sin[i]
            turned = ct * y - st * x  # y after Rz(θ)
            x = ct * x + st * y
            p = p + lengths[i] * x + d * z
            y, z = ca * turned + sa * z, ca * z - sa * turned
            frame = out[i + 1, :3]
            frame[:, 0], frame[:, 1], frame[:, 2], frame[:, 3] = x, y, z, p
        return np.moveaxis(out, (0, 1, 2), (-3, -2, -1))

    def fk(self, q: ArrayLike, delta: ArrayLike | None = None, a: ArrayLike | None = None) -> Array:
        """End-effector transform (..., 4, 4) (``a``: as :meth:`frames`)."""
        return self.frames(q, delta, a)[..., -1, :, :]

    def position(self, q: ArrayLike, delta: ArrayLike | None = None, a: ArrayLike | None = None) -> Array:
        """End-effector position (..., 3) (``a``: as :meth:`frames`)."""
        return self.fk(q, delta, a)[..., :3, 3]

    def jacobian(self, q: ArrayLike, delta: ArrayLike | None = None) -> Array:
        """Geometric position Jacobian (..., 3, n_actuated): z_{i−1} × (p_e − p_{i−1}) per actuated row."""
        frames = self.frames(q, delta)
        tip = frames[..., -1, :3, 3]
        cols = [
            np.cross(frames[..., i, :3, 2], tip - frames[..., i, :3, 3])
            for i, row in enumerate(self.rows)
            if row.actuated
        ]
        return np.stack(cols, -1)

    def rigid(self) -> RigidChain:
        """The rigid-body model (RBM): δ = 0, each run of virtual rows merged into one fixed transform."""
        return RigidChain(self)


class RigidChain:
    """Rigid-body model of a D-H chain: per actuated joint, Rz(q)·(its row's fixed part)·(the merged fixed
    transforms of the virtual rows that follow). An independent path to the same numbers at δ = 0."""

    def __init__(self, flexible: DHChain) -> None:
        self.actuated = flexible.actuated
        self.virtual: tuple[str, ...] = ()  # frozen at δ = 0
        self._lead = np.eye(4)  # virtual rows before the first actuated joint
        self._links: list[tuple[float, Array]] = []  # (offset, fixed transform after Rz(θ))
        for row in flexible.rows:
            at_zero = _dh_transforms(
                np.array(row.a), np.array(row.alpha), np.array(row.d), np.array(row.offset)
            )
            if row.actuated:
                fixed = _dh_transforms(np.array(row.a), np.array(row.alpha), np.array(row.d), np.array(0.0))
                self._links.append((row.offset, fixed))
            elif self._links:
                offset, fixed = self._links[-1]
                self._links[-1] = (offset, fixed @ at_zero)
            else:
                self._lead = self._lead @ at_zero

    def fk(self, q: ArrayLike) -> Array:
        """End-effector transform (..., 4, 4)."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1] != len(self.actuated):
            raise ValueError(f"q has {q.shape[-1]} values, the chain has actuated joints {self.actuated}")
        out = np.broadcast_to(self._lead, (*q.shape[:-1], 4, 4))
        for i, (offset, fixed) in enumerate(self._links):
            th = q[..., i] + offset
            rz = np.zeros((*q.shape[:-1], 4, 4))
            rz[..., 0, 0], rz[..., 0, 1], rz[..., 1, 0], rz[..., 1, 1] = (
                np.cos(th),
                -np.sin(th),
                np.sin(th),
                np.cos(th),
            )
            rz[..., 2, 2] = rz[..., 3, 3] = 1.0
            out = out @ rz @ fixed
        return out

    def position(self, q: ArrayLike) -> Array:
        """End-effector position (..., 3)."""
        return self.fk(q)[..., :3, 3]
