"""The simulated-time runner: plans executed on a batch of twin benches, much faster than real time.

Every plan of a batch runs on its own bench of one ``World`` (same robot description, its own device clocks
and noise), stepped together. Commands are applied every ``block_s`` of simulated time (what the plan holds
at that instant); every ``window_s`` the window's true trace is read through the device models, and every
``write_s`` what was read is written as the same topics the real-time recorder writes, one session per plan,
with host times offset by a fixed epoch. Benches whose plan has ended hold still and write nothing more.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.command_guard import CommandGuard, CommandRefused
from acquisition.plans.compensation import Compensator, compensator_for
from acquisition.plans.plan import Plan
from acquisition.recorder.sessions import SessionStore
from acquisition.recorder.writer import SessionWriter
from acquisition.safety import SafetyChecker
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.session_card import SESSION_CARD
from models.robot import RobotDescription
from twin.buffered_writer import BufferedSessionWriter
from twin.identity import IDENTITY, differences, recorded_identity, refuse, session_identity
from twin.kernel import Trace
from twin.streams import servo_current_a
from twin.topics import stream_rows
from twin.world import World

log = logging.getLogger(__name__)

SIM_EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: simulated sessions start here on the host clock
SIM_PREFIX = "sim-"  # the id of every simulated session starts so (a real-time one never does)


@dataclass(frozen=True)
class SimReport:
    sessions: list[str]  # session ids written (skipped ones not included)
    skipped: list[str]  # complete sessions already on disk
    simulated_s: float  # bench-seconds simulated (sum over benches)
    wall_s: float
    messages: int
    stopped: dict[str, str] = dataclasses.field(default_factory=dict)  # session id → why it stopped early

    @property
    def speedup(self) -> float:
        """Simulated bench-seconds per wall second."""
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")


TWIN_TRUTH = (
    "twin_truth"  # metadata key: what the twin knows and a lab never does (for checking the pipeline)
)


def twin_truth(world: World, bench: int) -> str:
    """JSON of the bench's true device clocks (t_dev = (1 + ε)·t + b) and fixed USB latencies, and where the
    tracker's field generator sits: the answers the pipeline's clock fits and registration are tested
    against. The pipeline itself never reads it."""
    import json

    robot = world.robot
    clocks = {
        name: {
            "drift_ppm": float(c.drift_ppm[bench]), "offset_s": float(c.offset_s[bench]),
            "tick_s": c.spec.tick_s, "wrap": c.spec.wrap,
            "latency_s": robot.devices[name].host_link.latency_s,
            "jitter_s": robot.devices[name].host_link.jitter_s,
        }
        for name, c in world.clocks.items()
    }  # fmt: skip
    tracker = robot.sensors.tracker
    placement = {
        "rpy_rad": list(tracker.base_to_tracker_rpy_rad),
        "translation_m": list(tracker.base_to_tracker_translation_m),
    }
    return json.dumps({"clocks": clocks, "base_to_tracker": placement, "host_epoch_ns": SIM_EPOCH_NS})


def session_id(plan: Plan) -> str:
    return SIM_PREFIX + plan.name.replace("/", "-")


def _complete(directory: Path) -> dict | None:
    """The card of this twin session if it was written whole. None when its session.json is missing or damaged
    (it is then simulated again, as an interrupted one is)."""
    from acquisition.recorder.sessions import SessionError, read_card

    if not (directory / SESSION_CARD).is_file():
        return None
    try:
        card = read_card(directory)
    except SessionError as exc:
        log.warning("simulated again: %s", exc)
        return None
    return card if card.get("status") == "complete" else None


def reusable(plans: list[Plan], robot: RobotDescription, sessions_dir: Path, seed: int,
             compensators: list[Compensator | None] | None = None) -> list[bool]:  # fmt: skip
    """Which plans' sessions are on disk, complete and made as this run would make them (robot, parameters,
    learned model, code): those are not simulated again. A complete one made otherwise:
    :class:`StaleSessionsError`."""
    done, stale = [], {}
    for p, c in zip(plans, compensators or [None] * len(plans), strict=True):
        card = _complete(sessions_dir / session_id(p))
        wanted = session_identity(p, robot, seed, c)
        differ = [] if card is None else differences(recorded_identity(card), wanted)
        if differ:
            stale[session_id(p)] = differ
        done.append(card is not None and not differ)
    refuse(stale, sessions_dir)
    return done


def _concat(traces: list[Trace]) -> Trace:
    return Trace(
        **{
            f.name: np.concatenate([getattr(tr, f.name) for tr in traces], axis=0 if f.name == "t" else 1)
            for f in dataclasses.fields(Trace)
        }
    )


def simulate(
    plans: list[Plan],
    robot: RobotDescription,
    sessions_dir: Path,
    seed: int = 0,
    block_s: float = 0.01,
    window_s: float = 1.0,
    write_s: float = 10.0,
    servo_rate_hz: float = 500.0,
    progress: Callable[[float], None] | None = None,
    compensators: list[Compensator | None] | None = None,
    check_safety: bool = True,
    plans_checked: bool = False,
) -> SimReport:
    """Run ``plans`` (all for ``robot``) as one batch; write one session per plan under ``sessions_dir``.

    ``compensators[i]`` (if given) turns plan i's goals into commands at each new set-point, from the bench's
    pressures and currents at that instant. With ``check_safety`` every plan is checked before anything runs
    (:class:`SafetyError`; ``plans_checked``: the caller has done it), and the benches' state while they
    run: a bench that breaks a limit gets a SAFETY_STOP event and its session ends there. A compensator's
    output passes the command guard before it is used: a goal that is not a number or outside the joints'
    ranges is never commanded; the bench holds where it is, a COMMAND_REFUSED and a SAFETY_STOP event say
    why, and its session ends there."""
    if any(p.robot != robot.name for p in plans):
        raise ValueError(f"every plan of a batch must be for {robot.name}")
    compensators = list(compensators) if compensators is not None else [None] * len(plans)
    if len(compensators) != len(plans):
        raise ValueError("one compensator (or None) per plan")
    done = reusable(plans, robot, sessions_dir, seed, compensators)
    skipped = [session_id(p) for p, d in zip(plans, done, strict=True) if d]
    plans, compensators = (
        [p for p, d in zip(plans, done, strict=True) if not d],
        [c for c, d in zip(compensators, done, strict=True) if not d],
    )
    start = time.perf_counter()
    if not plans:
        return SimReport([], skipped, 0.0, 0.0, 0)
    safety = SafetyChecker(robot) if check_safety else None
    if safety and not plans_checked:
        for p in plans:
            safety.require_safe(p)
    first = [p.at(np.array([0.0])) for p in plans]
    world = World(
        robot, batch=len(plans), seed=seed,
        q0=np.stack([f["goal_q"][0] for f in first]),
        pressure_pa=np.stack([f["pressure_pa"][0] for f in first]),
        payload_kg=np.array([f["payload_kg"][0] for f in first]),
    )  # fmt: skip
    default_speed = world.commands.profile_vel.copy()
    servo_joints = [i for i, j in enumerate(robot.joints) if j.drive != "stepper"]
    steps_per_block = max(1, round(block_s / world.dt))
    block_s = steps_per_block * world.dt
    blocks_per_window = max(1, round(window_s / block_s))
    end = max(p.duration_s for p in plans)
    durations = np.array([p.duration_s for p in plans])
    event_t = [np.array([t for t, _ in p.events]) for p in plans]
    writers = []
    compress_in = ThreadPoolExecutor(os.cpu_count() or 1, thread_name_prefix="compress")  # beside the loop
    sim_now = [0.0]  # the writers' clock: simulated seconds, so a session's bytes (its chunks) never depend
    # on how fast this machine ran it, and the same seed gives the same files
    for r, (p, c) in enumerate(zip(plans, compensators, strict=True)):
        directory = sessions_dir / session_id(p)
        if directory.exists():  # an incomplete earlier try: start it again
            for old in directory.glob("*"):
                old.unlink()
        w = SessionWriter(directory, robot, session_id(p), experiment=p.parameters.get("experiment", p.name),
                          metadata={"plan": p.name, "runner": "simulated", "seed": str(seed),
                                    "parameters": p.parameters, TWIN_TRUTH: twin_truth(world, r),
                                    IDENTITY: session_identity(p, robot, seed, c)},
                          flush_s=30.0, clock=lambda: sim_now[0], standard_batch_s=write_s,
                          compress_in=compress_in)  # fmt: skip
        w.open()
        w.event(Event(EventKind.SESSION_START, label=p.name), SIM_EPOCH_NS)
        writers.append(BufferedSessionWriter(w, write_s))
    topics = writers[0].topics
    last_goal = np.full(len(plans), -1)
    last_pressure = np.full(len(plans), -1)
    compensation = _Compensation(robot, plans, compensators, block_s)
    messages = 0
    stopped: dict[str, str] = {}
    t0 = 0.0
    try:
        while t0 < end - 1e-12:
            tb = t0 + block_s * np.arange(blocks_per_window)
            cmds = [p.at(tb) for p in plans]
            goal = np.stack([c["goal_q"] for c in cmds], axis=1)  # (nb, B, A)
            speed = np.stack([c["goal_speed"] for c in cmds], axis=1)
            speed = np.where(speed > 0, speed, default_speed[None])
            pressure = np.stack([c["pressure_pa"] for c in cmds], axis=1)
            valves = np.stack([c["valve_open"] for c in cmds], axis=1)
            payload = np.stack([c["payload_kg"] for c in cmds], axis=1)
            taps = _taps_by_block(plans, tb, block_s)  # (nb, B) angular impulses, N·m·s
            goal_index = np.stack([c["goal_index"] for c in cmds], axis=1)
            traces = []
            for b in range(blocks_per_window):
                compensation.apply(world, goal_index[b], goal[b], float(tb[b]))  # in place: what is sent
                world.command_joints(goal[b], profile_vel=speed[b])
                world.command_pressure(pressure[b])
                world.set_valves(valves[b])
                world.set_payload(payload[b])
                if taps[b].any():
                    world.tap(taps[b])
                traces.append(world.step(steps_per_block))
                compensation.observe(world)
            trace = _concat(traces)
            t1 = float(trace.t[-1])
            for r, c in enumerate(cmds):
                c["goal_q"] = goal[:, r]  # the goals as sent (compensated where a compensator is set)
            stops = _safety_stops(safety, plans, trace, payload, durations) if safety else {}
            refused = compensation.take_refusals()
            for r, (t_refused, event) in refused.items():
                if t_refused <= durations[r] and (r not in stops or t_refused <= stops[r][0]):
                    stops[r] = (t_refused, event)
            for r, (t_stop, event) in stops.items():
                durations[r] = t_stop  # the bench's session ends at the stop
                stopped[session_id(plans[r])] = f"{event.label}: {event.text}"
            rows = stream_rows(robot, topics, world.read(trace, servo_rate_hz), valves[-1])
            for r, (p, w) in enumerate(zip(plans, writers, strict=True)):
                if t0 >= durations[r] and r not in stops:  # a stop at t = 0 still writes its events
                    continue
                messages += _write_commands(w, topics, cmds[r], tb, last_goal, last_pressure, r, servo_joints)
                for topic, (robot_idx, host_ns, topic_rows) in rows.items():
                    lo, hi = np.searchsorted(robot_idx, [r, r + 1])
                    sel = slice(lo, hi)
                    if t1 > durations[r]:  # the plan ends in this window: nothing after its end
                        sel = lo + np.flatnonzero(host_ns[lo:hi] <= durations[r] * 1e9)
                    w.write(topic, SIM_EPOCH_NS + host_ns[sel], topic_rows[sel])
                    messages += len(topic_rows[sel])
                e_lo = np.searchsorted(event_t[r], t0, side="left")
                e_hi = np.searchsorted(
                    event_t[r], min(t1, durations[r]), "right" if t1 >= durations[r] else "left"
                )
                for t_event, event in p.events[e_lo:e_hi]:
                    w.event(event, SIM_EPOCH_NS + round(t_event * 1e9))
                    messages += 1
                if r in refused and stops.get(r) == refused[r]:
                    w.event(Event(EventKind.COMMAND_REFUSED, label="compensator", text=refused[r][1].text),
                            SIM_EPOCH_NS + round(refused[r][0] * 1e9))  # fmt: skip
                    messages += 1
                if r in stops:
                    w.event(stops[r][1], SIM_EPOCH_NS + round(stops[r][0] * 1e9))
                    messages += 1
            t0 = sim_now[0] = t1
            for w in writers:
                w.flush_if_due(t0)
            if progress:
                progress(min(1.0, t0 / end))
        for w, p, d in zip(writers, plans, durations, strict=True):
            w.event(Event(EventKind.SESSION_END, label=p.name), SIM_EPOCH_NS + round(d * 1e9))
    finally:
        try:
            for w, d in zip(writers, durations, strict=True):
                w.close("refused" if d <= 0 else "complete")  # refused at t = 0: nothing of the plan ran
        finally:
            compress_in.shutdown(cancel_futures=True)
    wall = time.perf_counter() - start
    return SimReport([session_id(p) for p in plans], skipped, float(durations.sum()), wall, messages, stopped)


class _Compensation:
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


def _safety_stops(
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


def _taps_by_block(plans: list[Plan], tb: np.ndarray, block_s: float) -> np.ndarray:
    """The plans' tap impulses summed into the blocks starting at ``tb`` (a tap acts at its block's start)."""
    out = np.zeros((len(tb), len(plans)))
    for r, p in enumerate(plans):
        t = p.tap_t
        sel = (t >= tb[0] - 1e-9) & (t < tb[-1] + block_s - 1e-9)
        if sel.any():
            k = np.clip(np.searchsorted(tb, t[sel] + 1e-9, side="right") - 1, 0, len(tb) - 1)
            np.add.at(out[:, r], k, p.tap_impulse_nms[sel])
    return out


def _write_commands(w: BufferedSessionWriter, topics, cmds: dict, tb: np.ndarray, last_goal, last_pressure,
                    r: int, servo_joints: list[int]) -> int:  # fmt: skip
    """Servo goals and pressure commands at the blocks where the plan changed them."""
    n = 0
    gi = cmds["goal_index"]
    new = np.flatnonzero(np.diff(np.concatenate([[last_goal[r]], gi])) != 0)
    if len(new):
        msg = topics[T.SERVO_GOAL].message
        rows = msg.pack(
            {
                "seq": gi[new],
                "position": cmds["goal_q"][new][:, servo_joints],
                "profile_velocity": cmds["goal_speed"][new][:, servo_joints],
                "profile_acceleration": np.zeros((len(new), len(servo_joints))),
            }
        )
        w.write(T.SERVO_GOAL, SIM_EPOCH_NS + np.rint(tb[new] * 1e9).astype(np.int64), rows)
        last_goal[r] = gi[-1]
        n += len(new)
    pi = cmds["pressure_index"]
    new = np.flatnonzero(np.diff(np.concatenate([[last_pressure[r]], pi])) != 0)
    if len(new):
        rows = topics[T.PRESSURE_COMMAND].message.pack(
            {"seq": pi[new], "setpoint": cmds["pressure_pa"][new], "valve_open": cmds["valve_open"][new]}
        )
        w.write(T.PRESSURE_COMMAND, SIM_EPOCH_NS + np.rint(tb[new] * 1e9).astype(np.int64), rows)
        last_pressure[r] = pi[-1]
        n += len(new)
    return n


def simulate_experiment(
    experiment: str,
    sessions: SessionStore,
    seed: int = 0,
    benches: int = 128,
    overrides: dict | None = None,
    progress: Callable[[str, float], None] | None = None,
    inverse_model: Callable[[Plan], Compensator] | None = None,
    prepared: tuple[dict[str, RobotDescription], list[Plan], dict] | None = None,
) -> list[SimReport]:
    """Expand an experiment (``configs/experiments/<name>.yaml`` + overrides) into plans and run them all on
    the twin, at most ``benches`` benches per batch, into the lab's ``sessions`` (a local store). Sessions
    already complete on disk are skipped.

    Experiment 2's ``hybrid`` and ``history`` plans need ``inverse_model``: it gives the compensator (a
    trained inverse model) for a plan, by its ``parameters["commands"]``; the layers above ``acquisition``
    (the pipeline's model store, the main job) provide it. It is called once per plan, so a compensator with
    memory starts each session afresh. ``prepared``: what :func:`prepare_experiment` gave for these
    arguments (a caller that checks before it commits to the work)."""
    kind, sessions_dir = Path(experiment).stem, sessions.root
    robots, plans, _ = prepared or prepare_experiment(experiment, overrides, benches, seed, inverse_model)
    batches = []  # (robot, plans, first plan's index in its robot's group, label)
    for name, robot in robots.items():
        group = [p for p in plans if p.robot == name]
        for k in range(0, len(group), benches):
            batch = group[k : k + benches]
            batches.append((robot, batch, k, f"{kind} {name} {k + 1}–{k + len(batch)}/{len(group)}"))
    compensators = [[compensator_for(p, r, inverse_model) for p in batch] for r, batch, _, _ in batches]
    for (robot, batch, k, _), c in zip(batches, compensators, strict=True):  # sessions of another making on
        reusable(batch, robot, sessions_dir, seed + k, c)  # disk: refused before any is written
    reports = []
    for (robot, batch, k, label), c in zip(batches, compensators, strict=True):
        tick = (lambda f, label=label: progress(label, f)) if progress else None
        run = dict(seed=seed + k, progress=tick, compensators=c, plans_checked=True)
        reports.append(simulate(batch, robot, sessions_dir, **run))
    return reports


def prepare_experiment(
    experiment: str, overrides: dict | None = None, benches: int = 128, seed: int = 0, inverse_model=None
) -> tuple[dict[str, RobotDescription], list[Plan], dict]:
    """An experiment's robots, plans and parameters, every one checked (parameters, size, duration, the
    robot's limits) before any session is written or any work starts."""
    from acquisition.plans.experiments import expand_experiment

    robots, plans, params = expand_experiment(experiment, overrides, benches=benches, seed=seed)
    commands = params["commands"] if Path(experiment).stem == "experiment2" else ()
    learned = [m for m in ("hybrid", "history") if m in commands]
    if learned and inverse_model is None:
        raise ValueError(
            f"experiment2: {' and '.join(learned)} commands need a trained inverse model (train one first, "
            "or run without them: --set 'commands=[ik,static]')"
        )
    for name, robot in robots.items():  # every plan of every robot, before any session is written
        checker = SafetyChecker(robot)
        for p in plans:
            if p.robot == name:
                checker.require_safe(p)
    return robots, plans, params
