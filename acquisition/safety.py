"""Safety limits: checked on a plan before it runs, and on the measured state while it runs.

Limits come from the robot description: the joints' ranges, the pneumatics' operating range, and its
``safety`` section (the tip's allowed box; how close to the wrinkling moment M_w(p) = (π²/8) p r³ an
inflatable link may be loaded — above M_w the link is non-linear, at M_c = 2 M_w it collapses). A protocol
that studies the non-linear range (POPUP's static link test) sets ``allow_wrinkling`` and is held below
``collapse_fraction`` · M_c instead.

A link whose valve is closed below the operating minimum is *stowed* (deflated, as before deployment): it is
not load-bearing, so its wrinkling limit does not apply, but no joint may move while it is stowed. Inflated
from there, it stays out of the wrinkling check until its measured pressure reaches the operating minimum, as
long as no joint has moved since it was stowed (a link filling in the pose it deployed in; at 0 kPa its
M_w is 0 and any moment breaks it). A plan that begins with a link stowed cannot move the arm to its start:
``check_start`` holds the measured bench to it (joints at the first pose, the stowed links deflated).

Every check is vectorised over samples. ``check_plan`` looks at every commanded instant (and at points between
consecutive joint goals); ``check_state`` at measured samples (the runners call it while a plan runs).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from acquisition.errors import AcquisitionError
from acquisition.schemas.events import Event, EventKind
from models.prbm import collapse_moment, wrinkling_moment
from models.robot import RobotDescription
from models.statics import gravity_moments, static_deflection

MOVE_SUBSAMPLES = 8  # points checked between two consecutive joint goals (a move sweeps through them)


class SafetyError(AcquisitionError, RuntimeError):
    """A plan breaks a safety limit; nothing has been commanded."""

    def __init__(self, plan: str, violations: list[Violation]) -> None:
        self.violations = violations
        shown = "\n".join(f"  {v}" for v in violations[:10])
        more = f"\n  … and {len(violations) - 10} more" if len(violations) > 10 else ""
        super().__init__(f"plan {plan} breaks {len(violations)} safety limit(s):\n{shown}{more}")


@dataclass(frozen=True)
class Violation:
    t_s: float  # plan time (check_plan) or the sample's time (check_state)
    limit: str  # "joint", "pressure", "workspace", "wrinkling", "collapse", "stowed-motion", "start"
    detail: str
    sample: int = -1  # which sample (check_state) or instant (check_plan)

    def __str__(self) -> str:
        return f"t = {self.t_s:.3f} s: {self.limit}: {self.detail}"


START_TOLERANCE_RAD = np.deg2rad(1.0)  # ASSUMED: a joint "at" a plan's start pose


class CheckedPlan(Protocol):
    """What the checks read of a plan (``acquisition.plans.plan.Plan`` is one): safety sits below the plans,
    which call it, so it names the fields it needs instead of importing them."""

    name: str
    robot: str
    duration_s: float
    goal_t: np.ndarray
    goal_q: np.ndarray
    goal_speed: np.ndarray
    pressure_t: np.ndarray
    pressure_pa: np.ndarray
    valve_open: np.ndarray
    payload_t: np.ndarray
    events: Sequence[tuple[float, Event]]
    parameters: dict

    def at(self, t: np.ndarray) -> dict[str, np.ndarray]: ...


class SafetyChecker:
    """The limits of one robot, ready to check plans and measured samples."""

    def __init__(self, robot: RobotDescription) -> None:
        self.robot = robot
        self.joint_limits = robot.joint_limits()
        pn = robot.pneumatics
        self.pressure_min, self.pressure_max = pn.min_operating_pa, pn.max_operating_pa
        spec = robot.safety
        self.tolerance_pa = spec.pressure_tolerance_pa if spec else 0.0
        self.box = (np.asarray(spec.workspace_min_m), np.asarray(spec.workspace_max_m)) if spec else None
        self.link_channels = sorted(
            {ln.pressure_channel for ln in robot.links if ln.pressure_channel is not None}
        )
        # inflatable links: (name, radius, channel, indices of its virtual joints among the chain's rows)
        rows = [r.joint for r in robot.dh_rows()]
        self.inflatable = [
            (ln.name, ln.radius_m, ln.pressure_channel, [rows.index(v) for v in ln.virtual_joints])
            for ln in robot.links
            if ln.radius_m is not None and ln.pressure_channel is not None
        ]
        self.wrinkling_fraction = spec.wrinkling_fraction if spec else 1.0
        self.collapse_fraction = spec.collapse_fraction if spec else 0.9

    # ------------------------------------------------------------------------------------------- plans
    def check_plan(self, plan: CheckedPlan) -> list[Violation]:
        """Every limit at every commanded instant of ``plan`` (static loads at rest in the commanded pose)."""
        if plan.robot != self.robot.name:
            raise ValueError(f"plan {plan.name} is for {plan.robot}, not {self.robot.name}")
        times = np.unique(np.concatenate([plan.goal_t, plan.pressure_t, plan.payload_t, self._moves(plan)]))
        cmd = plan.at(times)
        goal_q = cmd["goal_q"]
        q = self._swept(plan, times, cmd["goal_index"], goal_q)
        out = self._joints(plan.goal_t, plan.goal_q)  # a sweep between goals stays inside the joints' box
        pressure, valves = cmd["pressure_pa"], cmd["valve_open"]
        out += self._pressure_commands(times, pressure, valves)
        stowed = self._stowed(pressure, valves)
        goal_changes = np.flatnonzero(np.diff(cmd["goal_index"], prepend=-1) != 0)[1:]
        for k in goal_changes[stowed[goal_changes].any(axis=1)]:
            out.append(
                Violation(float(times[k]), "stowed-motion", "a joint goal changes while a link is deflated")
            )
        delta, _ = static_deflection(self.robot, q, pressure, cmd["payload_kg"])
        out += _at_points(plan, self._workspace(times, self.robot.chain().position(q, delta)))
        full = gravity_moments(self.robot, q, delta, cmd["payload_kg"])
        out += self._bending(times, full, pressure, stowed, bool(plan.parameters.get("allow_wrinkling")))
        return sorted(out, key=lambda v: v.t_s)

    def _swept(
        self, plan: CheckedPlan, times: np.ndarray, index: np.ndarray, goal_q: np.ndarray
    ) -> np.ndarray:
        """Where the joints are at ``times`` on their way to goal ``index``: each drive at its own profile
        speed until it arrives, so a joint with less to travel arrives first and the arm passes through
        poses off the straight line between the goals (a corner that may dip out of the box); a goal without
        a speed is swept linearly over its move."""
        prev_q = plan.goal_q[np.maximum(index - 1, 0)]
        start, end = plan.goal_t[index], self._goal_end(plan, index)
        elapsed = np.clip(times - start, 0.0, np.maximum(end - start, 0.0))[:, None]
        frac = elapsed / np.maximum(end - start, 1e-9)[:, None]
        step = goal_q - prev_q
        speed = plan.goal_speed[index]
        travelled = np.where(speed > 0, np.minimum(speed * elapsed, np.abs(step)), frac * np.abs(step))
        moving = (times > start)[:, None] & (end > start)[:, None]
        return np.where(moving, prev_q + np.sign(step) * travelled, goal_q)

    def require_safe(self, plan: CheckedPlan) -> None:
        """Raise :class:`SafetyError` if ``plan`` breaks any limit."""
        violations = self.check_plan(plan)
        if violations:
            raise SafetyError(plan.name, violations)

    @staticmethod
    def _goal_end(plan: CheckedPlan, index: np.ndarray) -> np.ndarray:
        """When the move towards goal ``index`` is expected to end: at the next goal's time, or after the
        joint distance at the profile speed (a ``goto`` followed by a wait)."""
        nxt = np.minimum(index + 1, len(plan.goal_t) - 1)
        distance = np.abs(plan.goal_q[index] - plan.goal_q[np.maximum(index - 1, 0)]).max(axis=1)
        speed = plan.goal_speed[index].max(axis=1)
        travel = np.where(speed > 0, distance / np.maximum(speed, 1e-9), 0.0)
        t_next = np.where(index + 1 < len(plan.goal_t), plan.goal_t[nxt], np.inf)
        return np.minimum(plan.goal_t[index] + travel, t_next)

    def _moves(self, plan: CheckedPlan) -> np.ndarray:
        """Instants within each move, so a sweep through a forbidden pose is caught: evenly spaced, and
        when each joint arrives at its goal (the corners of a move whose drives arrive one by one)."""
        idx = np.arange(1, len(plan.goal_t))
        if not len(idx):
            return np.empty(0)
        start, end = plan.goal_t[idx], self._goal_end(plan, idx)
        frac = np.arange(1, MOVE_SUBSAMPLES + 1) / MOVE_SUBSAMPLES
        t = start[:, None] + (end - start)[:, None] * frac[None]
        speed = plan.goal_speed[idx]
        travel = np.abs(plan.goal_q[idx] - plan.goal_q[idx - 1]) / np.where(speed > 0, speed, np.inf)
        arrive = np.minimum(start[:, None] + travel, end[:, None])
        return np.clip(np.concatenate([t.ravel(), arrive.ravel()]), 0.0, plan.duration_s)

    def stowed(self, plan: CheckedPlan, t: np.ndarray) -> np.ndarray:
        """(n, C): the links ``plan`` holds stowed at plan times ``t``: commanded closed below the operating
        minimum at some instant since the joint goal in force at ``t`` was sent (the plan moves no joint
        while a link is stowed, so a link filling from stowed counts until the arm next moves)."""
        t = np.atleast_1d(np.asarray(t, float))
        goal = np.searchsorted(plan.goal_t, t, side="right") - 1
        since = np.where(goal >= 0, plan.goal_t[np.maximum(goal, 0)], 0.0)
        first = np.maximum(np.searchsorted(plan.pressure_t, since, side="right") - 1, 0)
        last = np.searchsorted(plan.pressure_t, t, side="right")  # one past the frame in force at t
        frames = np.zeros((len(plan.pressure_t) + 1, plan.pressure_pa.shape[1]), int)
        frames[1:] = np.cumsum(self._stowed(plan.pressure_pa, plan.valve_open), axis=0)
        return frames[np.maximum(last, first)] - frames[first] > 0

    def _stowed(self, pressure: np.ndarray, valves: np.ndarray) -> np.ndarray:
        """(n, C): link channels closed below the operating minimum (deflated, not load-bearing)."""
        out = np.zeros(pressure.shape, bool)
        ch = self.link_channels
        out[:, ch] = ~valves[:, ch] & (pressure[:, ch] < self.pressure_min)
        return out

    def _pressure_commands(self, t: np.ndarray, pressure: np.ndarray, valves: np.ndarray) -> list[Violation]:
        high = np.argwhere(pressure > self.pressure_max)
        out = _found(t, high[:, 0], "pressure", [
            f"channel {c} set to {pressure[i, c]:.0f} Pa > {self.pressure_max:.0f} Pa" for i, c in high
        ])  # fmt: skip
        ch = np.array(self.link_channels, int)
        low = np.argwhere(valves[:, ch] & (pressure[:, ch] < self.pressure_min))
        least = f"{self.pressure_min:.0f} Pa"
        return out + _found(t, low[:, 0], "pressure", [
            f"link channel {ch[c]} open at {pressure[i, ch[c]]:.0f} Pa < {least}" for i, c in low
        ])  # fmt: skip

    def check_start(self, plan: CheckedPlan, q: np.ndarray, pressure: np.ndarray) -> list[Violation]:
        """What keeps ``plan`` from starting on the bench as measured (joints ``q`` (A,), link pressures
        (C,)): a plan that begins with a link stowed moves no joint before it is inflated, so each joint must
        already be within START_TOLERANCE_RAD of the first pose and each link stowed at the start deflated
        (below the operating minimum). Other plans start from anywhere (their first goal moves the arm)."""
        stowed = self._stowed(plan.pressure_pa[:1], plan.valve_open[:1])[0]
        if not stowed.any():
            return []
        names, first = self.robot.actuated_joints, plan.goal_q[0]
        out = []
        off = np.flatnonzero(np.abs(q - first) > START_TOLERANCE_RAD)
        if len(off):
            at = ", ".join(f"{names[j]} at {np.degrees(q[j]):.1f}°" for j in off)
            then = ", ".join(f"{np.degrees(first[j]):.1f}°" for j in off)
            out.append(Violation(0.0, "start", f"{at} (the plan starts at {then} and moves no joint while a "
                                 "link is deflated)"))  # fmt: skip
        full = sorted(
            (c, n) for n, _, c, _ in self.inflatable if stowed[c] and pressure[c] >= self.pressure_min
        )
        if full:
            at = ", ".join(f"{name} at {pressure[c] / 1e3:.1f} kPa" for c, name in full)
            why = f"the plan starts with {'it' if len(full) == 1 else 'them'} deflated, below"
            out.append(Violation(0.0, "start", f"{at} ({why} {self.pressure_min / 1e3:g} kPa)"))
        return out

    # --------------------------------------------------------------------------------- measured state
    def check_state(
        self,
        t: np.ndarray,
        q: np.ndarray,
        pressure: np.ndarray,
        payload_kg: np.ndarray | float,
        delta: np.ndarray | None = None,
        allow_wrinkling: np.ndarray | bool = False,
        every: bool = False,
        stowed: np.ndarray | None = None,
    ) -> list[Violation]:
        """Limits on measured samples: joints ``q`` (n, A), link pressures (n, C), the payload hanging now
        (per sample or one). The link bending δ is the true one on the twin, else the static estimate from
        k(p). ``allow_wrinkling`` may differ per sample. ``every``: all violations, not the first few.
        ``stowed``: (n, C) the links the plan holds stowed at each sample (:meth:`stowed`); those measured
        below the operating minimum bear no load.
        """
        t, q, pressure = np.atleast_1d(t), np.atleast_2d(q), np.atleast_2d(pressure)
        payload = np.broadcast_to(np.asarray(payload_kg, float), t.shape)
        keep = None if every else 3
        out = self._joints(t, q, keep)
        high = np.argwhere(pressure > self.pressure_max + self.tolerance_pa)
        out += _found(t, high[:, 0], "pressure", [
            f"channel {c} at {pressure[i, c]:.0f} Pa > {self.pressure_max:.0f} Pa" for i, c in high
        ], keep)  # fmt: skip
        if delta is None:
            delta, _ = static_deflection(self.robot, q, pressure, payload)
        out += self._workspace(t, self.robot.chain().position(q, delta), keep)
        moments = gravity_moments(self.robot, q, delta, payload)
        limp = np.zeros(pressure.shape, bool) if stowed is None else stowed & (pressure < self.pressure_min)
        out += self._bending(t, moments, pressure, limp, allow_wrinkling, keep)
        return sorted(out, key=lambda v: v.t_s)

    # ------------------------------------------------------------------------------------------ limits
    def _joints(self, t: np.ndarray, q: np.ndarray, keep: int | None = 3) -> list[Violation]:
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        bad = np.argwhere((q < lo - 1e-9) | (q > hi + 1e-9))
        names = self.robot.actuated_joints
        return _found(t, bad[:, 0], "joint", [
            f"{names[j]} at {q[i, j]:.4f} rad, limits [{lo[j]:.4f}, {hi[j]:.4f}]" for i, j in bad
        ], keep)  # fmt: skip

    def _workspace(self, t: np.ndarray, tip: np.ndarray, keep: int | None = 3) -> list[Violation]:
        if self.box is None:
            return []
        lo, hi = self.box
        bad = np.flatnonzero(((tip < lo) | (tip > hi)).any(axis=1))
        box = f"{np.round(lo * 1e3).tolist()}–{np.round(hi * 1e3).tolist()} mm"
        return _found(t, bad, "workspace", [
            f"tip at {np.round(tip[i] * 1e3, 1).tolist()} mm, outside {box}" for i in bad
        ], keep)  # fmt: skip

    def _bending(self, t: np.ndarray, moments: np.ndarray, pressure: np.ndarray, stowed: np.ndarray,
                 allow_wrinkling: np.ndarray | bool, keep: int | None = 3) -> list[Violation]:  # fmt: skip
        """Each inflatable link's bending moment (the vector sum over its virtual joints' axes) against
        M_w(p) — or, where wrinkling is allowed (per sample), M_c(p)."""
        out = []
        allow = np.broadcast_to(np.asarray(allow_wrinkling, bool), t.shape)
        for name, radius, channel, rows in self.inflatable:
            bending = np.linalg.norm(moments[:, rows], axis=1)
            p = np.maximum(pressure[:, channel], 0.0)
            limit = np.where(
                allow,
                self.collapse_fraction * collapse_moment(p, radius),
                self.wrinkling_fraction * wrinkling_moment(p, radius),
            )
            bad = (bending > limit) & ~stowed[:, channel]
            for kind, mask in (("wrinkling", bad & ~allow), ("collapse", bad & allow)):
                idx = np.flatnonzero(mask)
                out += _found(t, idx, kind, [
                    f"{name} bends with {bending[i]:.2f} N·m > {limit[i]:.2f} N·m at {p[i] / 1e3:.1f} kPa"
                    for i in idx
                ], keep)  # fmt: skip
        return out


def _at_points(plan: CheckedPlan, violations: list[Violation]) -> list[Violation]:
    """``violations`` of ``plan`` naming the settled point each one is at or on the way to (a plan that
    settles at numbered points: the campaign's), so a refused point can be found and left out."""
    settled = [(t, e.index) for t, e in plan.events if e.kind == EventKind.SETTLED and e.index >= 0]
    if not settled:
        return violations
    times = np.array([t for t, _ in settled])
    out = []
    for v in violations:
        k = int(np.searchsorted(times, v.t_s - 1e-9))  # the first point settled at or after the violation
        where = f" (on the way to or at point {settled[k][1]})" if k < len(settled) else ""
        out.append(Violation(v.t_s, v.limit, v.detail + where, v.sample))
    return out


def _found(t: np.ndarray, samples: np.ndarray, limit: str, details: list[str], keep: int | None = 3):
    """Violations of one limit at ``samples``; only the first ``keep`` (a slow move past a limit breaks it at
    many instants) and a count of the rest, unless ``keep`` is None."""
    out = [Violation(float(t[i]), limit, d, int(i)) for i, d in zip(samples, details, strict=True)]
    if keep is None or len(out) <= keep:
        return out
    last = out[keep - 1]
    return [*out[:keep], Violation(last.t_s, limit, f"… and {len(out) - keep} more instants", last.sample)]
