"""Experiments as data: a plan is the timed actions of one bench, in plan time (seconds from its start).

Actions are kept as columns (times and values), so a runner can look up "what is commanded at time t" for a
whole batch of benches with ``searchsorted``, and a plan can be saved, diffed and checked before it runs:

- joint goals (rad) with their profile velocities (rad/s, 0 = the servo's default);
- pressure set-points (Pa) and valve states per channel;
- payload changes (kg): the operator hangs a mass (hardware: prompted and confirmed; twin: applied);
- hammer taps (N·m·s angular impulse on the tested link; hardware: prompted; twin: ``World.tap``);
- events: repetition start/end, settled points, notes — written to the session's events topic.

Build one with ``PlanBuilder``: ``b.goto(q).settle(2.0).follow(setpoints).mark(...)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from acquisition.schemas.events import Event, EventKind


@dataclass(frozen=True)
class Plan:
    name: str  # e.g. "experiment1/curve/vsl-1.5bar/25g"
    robot: str
    duration_s: float
    goal_t: np.ndarray  # (n,)
    goal_q: np.ndarray  # (n, A) rad, every actuated joint
    goal_speed: np.ndarray  # (n, A) rad/s profile velocity, 0 = the drive's default
    pressure_t: np.ndarray  # (m,)
    pressure_pa: np.ndarray  # (m, C)
    valve_open: np.ndarray  # (m, C) bool
    payload_t: np.ndarray  # (k,)
    payload_kg: np.ndarray  # (k,)
    events: tuple[tuple[float, Event], ...]
    parameters: dict = field(default_factory=dict)  # what the protocol was asked for (for the session card)
    tap_t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (j,) may be empty
    tap_impulse_nms: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (j,) angular impulses

    def __post_init__(self) -> None:
        if len(self.tap_t) != len(self.tap_impulse_nms):
            raise ValueError(f"plan {self.name}: tap_t and tap_impulse_nms differ in length")
        if len(self.tap_t) and (
            np.any(np.diff(self.tap_t) < 0) or self.tap_t[0] < 0 or self.tap_t[-1] > self.duration_s
        ):
            raise ValueError(f"plan {self.name}: tap times must be in order and within the plan")
        for name in ("goal", "pressure", "payload"):
            t = getattr(self, f"{name}_t")
            if len(t) == 0:
                raise ValueError(f"plan {self.name}: no {name} action (a plan starts by setting every input)")
            if np.any(np.diff(t) < 0) or t[0] != 0.0:
                raise ValueError(f"plan {self.name}: {name} times must start at 0 and never go back")
            if t[-1] > self.duration_s:
                raise ValueError(f"plan {self.name}: a {name} action comes after the plan's end")

    def at(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """What is commanded at plan times ``t``: the latest action at or before each time."""
        if np.any(np.asarray(t) < 0):
            raise ValueError(f"plan {self.name}: nothing is commanded before time 0")
        g = np.searchsorted(self.goal_t, t, side="right") - 1
        p = np.searchsorted(self.pressure_t, t, side="right") - 1
        m = np.searchsorted(self.payload_t, t, side="right") - 1
        return {
            "goal_index": g,
            "goal_q": self.goal_q[g],
            "goal_speed": self.goal_speed[g],
            "pressure_index": p,
            "pressure_pa": self.pressure_pa[p],
            "valve_open": self.valve_open[p],
            "payload_kg": self.payload_kg[m],
        }


class PlanBuilder:
    """Append actions at a moving cursor; ``build()`` freezes them into a ``Plan``."""

    def __init__(self, name: str, robot: str, joints: int, channels: int, parameters: dict | None = None):
        self.name, self.robot = name, robot
        self.joints, self.channels = joints, channels
        self.parameters = dict(parameters or {})
        self.t = 0.0
        self._goals: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._pressures: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._payloads: list[tuple[float, float]] = []
        self._taps: list[tuple[float, float]] = []
        self._events: list[tuple[float, Event]] = []

    def goto(self, q: np.ndarray, speed: np.ndarray | float = 0.0) -> PlanBuilder:
        """New joint goals now (the drives move with their profile velocity ``speed``)."""
        q = np.asarray(q, float).reshape(self.joints)
        self._goals.append((self.t, q, np.broadcast_to(np.asarray(speed, float), q.shape).copy()))
        return self

    def follow(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray) -> PlanBuilder:
        """Timed set-points from now (seed 000's Move(q, q̇): each goal with its joint speed, held until the
        next one's time). The cursor ends at the last set-point."""
        t = np.asarray(t, float) - t[0]
        for k in range(len(t)):
            self._goals.append((self.t + t[k], np.asarray(q[k], float), np.abs(np.asarray(qd[k], float))))
        self.t += float(t[-1])
        return self

    def pressure(self, pa: np.ndarray | float, valve_open: np.ndarray | bool = True) -> PlanBuilder:
        pa = np.broadcast_to(np.asarray(pa, float), (self.channels,)).copy()
        valves = np.broadcast_to(np.asarray(valve_open, bool), (self.channels,)).copy()
        self._pressures.append((self.t, pa, valves))
        return self

    def payload(self, kg: float) -> PlanBuilder:
        self._payloads.append((self.t, float(kg)))
        self._events.append(
            (self.t, Event(EventKind.PAYLOAD, value=float(kg), text=f"payload {kg * 1e3:g} g"))
        )
        return self

    def tap(self, impulse_nms: float) -> PlanBuilder:
        """A hammer tap now (angular impulse on the tested link), marked by a PLAN_STEP event 'tap'."""
        self._events.append(
            (self.t, Event(EventKind.PLAN_STEP, len(self._taps), float(impulse_nms), "tap", "hammer tap"))
        )
        self._taps.append((self.t, float(impulse_nms)))
        return self

    def wait(self, seconds: float) -> PlanBuilder:
        if seconds < 0:
            raise ValueError(f"cannot wait a negative time ({seconds} s)")
        self.t += seconds
        return self

    def settle(self, seconds: float, index: int = -1, hold_s: float = 0.0) -> PlanBuilder:
        """Wait for the bench to settle, then (``hold_s`` > 0) hold still while it is measured: the SETTLED
        event marks the start of the hold window, which the pipeline averages into one static point."""
        self.wait(seconds)
        self._events.append((self.t, Event(EventKind.SETTLED, index=index, value=hold_s)))
        return self.wait(hold_s)

    def mark(self, kind: EventKind, index: int = -1, label: str = "", text: str = "", value=float("nan")):
        self._events.append((self.t, Event(kind, index, value, label, text)))
        return self

    def build(self) -> Plan:
        def cols(items, width):
            t = np.array([i[0] for i in items], float)
            return (t, *(np.array([i[k] for i in items]).reshape(len(items), width) for k in (1, 2)))

        goal_t, goal_q, goal_speed = cols(self._goals, self.joints)
        pressure_t, pressure_pa, valves = cols(self._pressures, self.channels)
        events = sorted(self._events, key=lambda e: e[0])
        return Plan(
            self.name, self.robot, self.t, goal_t, goal_q, goal_speed, pressure_t, pressure_pa,
            valves.astype(bool), np.array([p[0] for p in self._payloads], float),
            np.array([p[1] for p in self._payloads], float), tuple(events), self.parameters,
            np.array([t[0] for t in self._taps], float), np.array([t[1] for t in self._taps], float),
        )  # fmt: skip
