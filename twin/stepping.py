"""Stepping a batch of twin benches one window at a time (the simulated-time runner's physics half): each
block's commands (compensated where a plan has a compensator, refused ones held), the kernel, the safety
checks of the benches' state, and the devices' readings as session topic rows. ``twin.runner`` writes them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from acquisition.command_guard import CommandGuard, CommandRefused
from acquisition.plans.compensation import Compensator
from acquisition.plans.plan import Plan
from acquisition.safety import SafetyChecker
from acquisition.schemas.events import Event, EventKind
from models.robot import RobotDescription
from models.statics import servo_current_a
from twin.kernel import Trace
from twin.topics import stream_rows
from twin.world import World


@dataclass
class Window:
    """One window of a batch, stepped: what its writes need."""

    t0: float
    t1: float
    tb: np.ndarray  # the blocks' start times
    commands: dict[str, np.ndarray]  # the plans' commands at the blocks, (blocks, benches, ...): goal_index,
    # goal_q (the goals as sent: compensated where a compensator is set), goal_speed, pressure_index,
    # pressure_pa, valve_open
    rows: dict  # topic → (bench index, host ns, rows) of every device stream
    stops: dict[int, tuple[float, Event]]  # bench → (time, event) of a stop in this window
    refused: dict[int, tuple[float, Event]]  # bench → (time, stop event) of a refused compensator command
    durations: np.ndarray  # each bench's session length after this window's stops


class Stepper:
    """Steps a batch's world one window at a time: commands at each block, the kernel, the safety checks and
    the devices' readings (``step``). Owns the world and the benches' durations (a stop shortens one)."""

    def __init__(self, world: World, plans: list[Plan], compensation: Compensation,
                 safety: SafetyChecker | None, topics: dict, durations: np.ndarray, steps_per_block: int,
                 blocks_per_window: int, servo_rate_hz: float) -> None:  # fmt: skip
        self.world, self.plans, self.compensation, self.safety = world, plans, compensation, safety
        self.topics, self.durations = topics, durations
        self.steps_per_block, self.blocks_per_window = steps_per_block, blocks_per_window
        self.block_s = steps_per_block * world.dt
        self.servo_rate_hz = servo_rate_hz
        self.default_speed = world.commands.profile_vel.copy()
        self.stopped: dict[int, str] = {}  # bench → why its session stopped early

    def step(self, t0: float) -> Window:
        world, plans, compensation, durations = self.world, self.plans, self.compensation, self.durations
        tb = t0 + self.block_s * np.arange(self.blocks_per_window)
        cmds = [p.at(tb) for p in plans]
        goal = np.stack([c["goal_q"] for c in cmds], axis=1)  # (nb, B, A)
        goal_speed = np.stack([c["goal_speed"] for c in cmds], axis=1)
        speed = np.where(goal_speed > 0, goal_speed, self.default_speed[None])
        pressure = np.stack([c["pressure_pa"] for c in cmds], axis=1)
        valves = np.stack([c["valve_open"] for c in cmds], axis=1)
        payload = np.stack([c["payload_kg"] for c in cmds], axis=1)
        taps = taps_by_block(plans, tb, self.block_s)  # (nb, B) angular impulses, N·m·s
        goal_index = np.stack([c["goal_index"] for c in cmds], axis=1)
        traces = []
        for b in range(self.blocks_per_window):
            compensation.apply(world, goal_index[b], goal[b], float(tb[b]))  # in place: what is sent
            world.command_joints(goal[b], profile_vel=speed[b])
            world.command_pressure(pressure[b])
            world.set_valves(valves[b])
            world.set_payload(payload[b])
            if taps[b].any():
                world.tap(taps[b])
            traces.append(world.step(self.steps_per_block))
            compensation.observe(world)
        trace = concat_traces(traces)
        stops = safety_stops(self.safety, plans, trace, payload, durations) if self.safety else {}
        refused = compensation.take_refusals()
        for r, (t_refused, event) in refused.items():
            if t_refused <= durations[r] and (r not in stops or t_refused <= stops[r][0]):
                stops[r] = (t_refused, event)
        for r, (t_stop, event) in stops.items():
            durations[r] = t_stop  # the bench's session ends at the stop
            self.stopped[r] = f"{event.label}: {event.text}"
        rows = stream_rows(world.robot, self.topics, world.read(trace, self.servo_rate_hz), valves[-1])
        commands = {"goal_index": goal_index, "goal_q": goal, "goal_speed": goal_speed,
                    "pressure_pa": pressure, "valve_open": valves,
                    "pressure_index": np.stack([c["pressure_index"] for c in cmds], axis=1)}  # fmt: skip
        return Window(t0, float(trace.t[-1]), tb, commands, rows, stops, refused, durations.copy())


class Compensation:
    """Per bench: the command sent for the active set-point, computed once when the set-point changes from
    the bench's link pressures and its joint currents low-passed over ``current_filter_s`` (the currents of a
    servo stepping along a path carry its accelerations; the compensators are fitted on settled currents)."""

    def __init__(self, robot: RobotDescription, plans: list[Plan], compensators: list[Compensator | None],
                 block_s: float, current_filter_s: float = 0.2):  # fmt: skip
        self.robot = robot
        self.benches = [r for r, c in enumerate(compensators) if c is not None]
        self.compensators = compensators
        self.index = np.full(len(plans), -1)
        self.command = np.zeros((len(plans), len(robot.actuated_joints)))
        self.alpha = min(1.0, block_s / current_filter_s)
        self.current: np.ndarray | None = None
        self.guard = CommandGuard(robot)
        self.halted: set[int] = set()
        self.refusals: dict[int, tuple[float, Event]] = {}

    def observe(self, world: World) -> None:
        """Update the low-passed currents after a block (an exponential moving average)."""
        if not self.benches:
            return
        now = servo_current_a(self.robot.servo, world.state.torque, world.state.out_vel)
        self.current = now if self.current is None else self.current + self.alpha * (now - self.current)

    def apply(self, world: World, goal_index: np.ndarray, goal: np.ndarray, t: float) -> None:
        """Replace the compensated benches' goals (B, A) in place; a refused command holds the bench where
        it is (kept for :meth:`take_refusals`)."""
        if not self.benches:
            return
        if self.current is None:
            self.observe(world)
        for r in self.benches:
            if goal_index[r] != self.index[r]:
                self.index[r] = goal_index[r]
                if r in self.halted:
                    continue
                try:
                    out = np.asarray(self.compensators[r](
                        goal[r][None], world.state.p_link[r][None], self.current[r][None], t_s=t
                    ), float)  # fmt: skip
                    if out.shape != (1, goal.shape[1]):
                        raise CommandRefused(
                            f"the compensator returned shape {out.shape} for one set of goals"
                        )
                    self.command[r] = self.guard.joint_goals(out[0])
                except CommandRefused as exc:
                    self.halted.add(r)
                    self.command[r] = world.state.out_pos[r]  # hold where it is
                    self.refusals[r] = (
                        t,
                        Event(EventKind.SAFETY_STOP, label="command", text=f"refused: {exc}"),
                    )
            goal[r] = self.command[r]

    def take_refusals(self) -> dict[int, tuple[float, Event]]:
        """The benches whose compensator gave a refused command since the last call: (time, stop event)."""
        out, self.refusals = self.refusals, {}
        return out


def safety_stops(
    safety: SafetyChecker, plans: list[Plan], trace: Trace, payload: np.ndarray,
    durations: np.ndarray, rate_hz: float = 20.0,
) -> dict[int, tuple[float, Event]]:  # fmt: skip
    """The first limit each running bench broke in this window (true state sampled at ``rate_hz``);
    ``payload``: every block's (nb, B)."""
    steps_per_block = len(trace.t) // payload.shape[0]
    step = max(1, round(1.0 / (rate_hz * (trace.t[1] - trace.t[0])))) if len(trace.t) > 1 else 1
    idx = np.arange(step - 1, len(trace.t), step)
    benches, n = trace.q.shape[0], len(idx)

    def flat(x: np.ndarray) -> np.ndarray:  # (B, steps, k) at the sampled steps → (B·n, k)
        return x[:, idx].reshape(benches * n, -1)

    def per_block(x: np.ndarray) -> np.ndarray:  # (nb, B, k) at the sampled steps' blocks → (B·n, k)
        return np.swapaxes(x[idx // steps_per_block], 0, 1).reshape(benches * n, -1)

    allow = np.array([bool(p.parameters.get("allow_wrinkling")) for p in plans])
    stowed = np.concatenate([safety.stowed(plan, trace.t[idx]) for plan in plans])
    violations = safety.check_state(
        np.tile(trace.t[idx], benches), flat(trace.q), flat(trace.pressure),
        per_block(payload[..., None])[:, 0], flat(trace.delta),
        allow_wrinkling=np.repeat(allow, n), every=True, stowed=stowed,
    )  # fmt: skip
    stops: dict[int, tuple[float, Event]] = {}
    for v in violations:
        r = v.sample // n
        if v.t_s > durations[r] or r in stops:
            continue
        stops[r] = (v.t_s, Event(EventKind.SAFETY_STOP, label=v.limit, text=v.detail))
    return stops


def taps_by_block(plans: list[Plan], tb: np.ndarray, block_s: float) -> np.ndarray:
    """The plans' tap impulses summed into the blocks starting at ``tb`` (a tap acts at its block's start)."""
    out = np.zeros((len(tb), len(plans)))
    for r, p in enumerate(plans):
        t = p.tap_t
        sel = (t >= tb[0] - 1e-9) & (t < tb[-1] + block_s - 1e-9)
        if sel.any():
            k = np.clip(np.searchsorted(tb, t[sel] + 1e-9, side="right") - 1, 0, len(tb) - 1)
            np.add.at(out[:, r], k, p.tap_impulse_nms[sel])
    return out


def concat_traces(traces: list[Trace]) -> Trace:
    return Trace(
        **{
            f.name: np.concatenate([getattr(tr, f.name) for tr in traces], axis=0 if f.name == "t" else 1)
            for f in dataclasses.fields(Trace)
        }
    )
