"""The simulated-time runner: plans executed on a batch of twin benches, much faster than real time.

Every plan of a batch runs on its own bench of one ``World`` (same robot description, its own device clocks
and noise), stepped together. Commands are applied every ``block_s`` of simulated time (what the plan holds
at that instant); every ``window_s`` the window's true trace is read through the device models, and every
``write_s`` what was read is written as the same topics the real-time recorder writes, one session per plan,
with host times offset by a fixed epoch. Benches whose plan has ended hold still and write nothing more.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import itertools
import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.plans.compensation import Compensator, compensator_for
from acquisition.plans.plan import Plan
from acquisition.recorder.sessions import SessionStore
from acquisition.safety import SafetyChecker
from acquisition.schemas.session_card import SESSION_CARD
from acquisition.schemas.topics import session_topics
from models.robot import RobotDescription
from twin.identity import IDENTITY, differences, recorded_identity, refuse, session_identity
from twin.session_writers import SIM_EPOCH_NS, BatchWriters, SessionSpec
from twin.stepping import Compensation, Stepper
from twin.world import World

log = logging.getLogger(__name__)

SIM_PREFIX = "sim-"  # the id of every simulated session starts so (a real-time one never does)
# a part of a batch for a worker process: at least this many bench-seconds (~3 s of one process's work at
# ~800× real time; a worker takes ~1–2 s to start and load the kernel)
PART_MIN_S = 2000.0


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
        payload_kg=np.array([f["payload_kg"][0] for f in first]), benches=[session_id(p) for p in plans],
    )  # fmt: skip
    steps_per_block = max(1, round(block_s / world.dt))
    block_s = steps_per_block * world.dt
    blocks_per_window = max(1, round(window_s / block_s))
    end = max(p.duration_s for p in plans)
    durations = np.array([p.duration_s for p in plans])
    specs = [
        SessionSpec(sessions_dir / session_id(p), session_id(p), p.parameters.get("experiment", p.name),
                    {"plan": p.name, "runner": "simulated", "seed": str(seed), "parameters": p.parameters,
                     TWIN_TRUTH: twin_truth(world, r), IDENTITY: session_identity(p, robot, seed, c)},
                    (p.name, SIM_EPOCH_NS))
        for r, (p, c) in enumerate(zip(plans, compensators, strict=True))
    ]  # fmt: skip
    batch = BatchWriters(robot, plans, specs, write_s)
    compensation = Compensation(robot, plans, compensators, block_s)
    stepper = Stepper(world, plans, compensation, safety, session_topics(robot), durations, steps_per_block,
                      blocks_per_window, servo_rate_hz)  # fmt: skip
    finished = False
    try:
        t0 = 0.0
        while t0 < end - 1e-12:
            window = stepper.step(t0)
            batch.write_window(window)
            t0 = window.t1
            if progress:
                progress(min(1.0, t0 / end))
        finished = True
    finally:
        messages = batch.end(durations, finished)
    wall = time.perf_counter() - start
    return SimReport([session_id(p) for p in plans], skipped, float(durations.sum()), wall, messages,
                     {session_id(plans[r]): why for r, why in stepper.stopped.items()})  # fmt: skip


def simulate_experiment(
    experiment: str,
    sessions: SessionStore,
    seed: int = 0,
    benches: int = 128,
    overrides: dict | None = None,
    progress: Callable[[str, float], None] | None = None,
    inverse_model: Callable[[Plan], Compensator] | None = None,
    prepared: tuple[dict[str, RobotDescription], list[Plan], dict] | None = None,
    processes: int = 1,
) -> list[SimReport]:
    """Expand an experiment (``configs/experiments/<name>.yaml`` + overrides) into plans and run them all on
    the twin, at most ``benches`` benches per batch, into the lab's ``sessions`` (a local store). Sessions
    already complete on disk are skipped.

    Experiment 2's ``hybrid`` and ``history`` plans need ``inverse_model``: it gives the compensator (a
    trained inverse model) for a plan, by its ``parameters["commands"]``; the layers above ``acquisition``
    (the pipeline's model store, the main job) provide it. It is called once per plan, so a compensator with
    memory starts each session afresh. ``prepared``: what :func:`prepare_experiment` gave for these
    arguments (a caller that checks before it commits to the work).

    ``processes`` > 1: each batch's plans still to simulate are cut into that many parts, each simulated in
    a worker process (its kernel on one thread): the same sessions, byte for byte (each bench draws its own
    noise), with every core busy (one process keeps ~1.4 cores so: writing is one thread). Its ``progress``
    moves as the parts end. An experiment with a learned ``inverse_model`` runs here (its compensators are
    not sent to workers). Returns a report per batch, or per part."""
    kind, sessions_dir = Path(experiment).stem, sessions.root
    robots, plans, _ = prepared or prepare_experiment(
        experiment, overrides, benches, seed, inverse_model, sessions_dir
    )
    batches = []  # (robot, plans, label); each bench draws its own noise: the batches change no data
    for name, robot in robots.items():
        group = [p for p in plans if p.robot == name]
        for k in range(0, len(group), benches):
            batch = group[k : k + benches]
            batches.append((robot, batch, f"{kind} {name} {k + 1}–{k + len(batch)}/{len(group)}"))
    compensators = [[compensator_for(p, r, inverse_model) for p in batch] for r, batch, _ in batches]
    for (robot, batch, _), c in zip(batches, compensators, strict=True):  # sessions of another making on
        reusable(batch, robot, sessions_dir, seed, c)  # disk: refused before any is written
    if processes > 1 and inverse_model is None:
        return _in_parts(batches, sessions_dir, seed, processes, progress)
    reports = []
    for (robot, batch, label), c in zip(batches, compensators, strict=True):
        tick = (lambda f, label=label: progress(label, f)) if progress else None
        run = dict(seed=seed, progress=tick, compensators=c, plans_checked=True)
        reports.append(simulate(batch, robot, sessions_dir, **run))
    return reports


def _in_parts(batches: list, sessions_dir: Path, seed: int, processes: int,
              progress: Callable[[str, float], None] | None) -> list[SimReport]:  # fmt: skip
    """The batches' plans not yet complete cut into ``processes`` parts each, simulated in worker processes
    (:func:`simulate_experiment`'s ``processes``); the progress of a batch is the share of its parts ended."""
    parts, skipped = [], []  # (label, robot, plans); the sessions already complete
    for robot, batch, label in batches:
        todo = [p for p in batch if _complete(sessions_dir / session_id(p)) is None]
        skipped += [session_id(p) for p in batch if p not in todo]
        n = min(processes, len(todo), max(1, int(sum(p.duration_s for p in todo) // PART_MIN_S)))
        cuts = np.linspace(0, len(todo), n + 1).round().astype(int)
        parts += [(label, robot, todo[a:b]) for a, b in itertools.pairwise(cuts)]
    done = [SimReport([], skipped, 0.0, 0.0, 0)] if skipped else []
    if len(parts) < 2:  # nothing to share the cores with: here, the kernel on every core
        return done + [simulate(plans, robot, sessions_dir, seed=seed, plans_checked=True)
                       for _, robot, plans in parts]  # fmt: skip
    with _kernel_workers(min(processes, len(parts))) as pool:
        futures = [pool.submit(simulate, plans, robot, sessions_dir, seed=seed, plans_checked=True)
                   for _, robot, plans in parts]  # fmt: skip
        ended = dict.fromkeys((label for label, _, _ in parts), 0)
        for future in cf.as_completed(futures):
            future.result()  # an error: raised once the parts under way have stopped
            label = parts[futures.index(future)][0]
            ended[label] += 1
            if progress:
                progress(label, ended[label] / sum(1 for other, _, _ in parts if other == label))
        return done + [f.result() for f in futures]


@dataclass(frozen=True)
class Simulation:
    """One experiment to simulate into a session store (its ``overrides`` as ``vslab simulate --set`` takes
    them; ``inverse_model`` as :func:`simulate_experiment` takes it: a simulation with one runs in the
    calling process, its compensators are not sent to a worker)."""

    experiment: str
    sessions: SessionStore
    overrides: dict | None = None
    inverse_model: Callable[[Plan], Compensator] | None = None

    def run(self, seed: int) -> list[SimReport]:
        return simulate_experiment(self.experiment, self.sessions, seed=seed, overrides=self.overrides,
                                   inverse_model=self.inverse_model)  # fmt: skip

    def pending(self, seed: int) -> bool:
        """Whether any plan has no complete session in the store yet (planned, not checked)."""
        from acquisition.plans.experiments import expand_experiment

        _, plans, _ = expand_experiment(self.experiment, self.overrides, benches=128, seed=seed)  # as run
        return any(_complete(self.sessions.root / session_id(p)) is None for p in plans)


def simulate_side_by_side(
    simulations: list[Simulation], seed: int = 0, processes: int = 2
) -> list[list[SimReport]]:
    """Experiments that do not depend on each other simulated at once, each whole in one of ``processes``
    worker processes: every session as :func:`simulate_experiment` writes it, in less time where a core is
    free.

    One simulated experiment keeps ~1.4 of 2 cores busy (writing is one thread; the kernel's parallel steps
    wait for their slowest thread); two side by side, each kernel on one thread (the benches are stepped
    independently: the same numbers), fill both. The experiments are taken in the order given, so put the
    longest first; experiments with every session complete already are only checked, here (no worker is
    started for them). An error in one (or Ctrl-C) is raised once the experiments under way have stopped;
    those still queued are dropped. Returns each experiment's reports, in the order given."""
    todo = []  # one alone is not planned twice to find out whether it has work
    if len(simulations) > 1 and processes > 1:
        todo = [k for k, s in enumerate(simulations) if s.inverse_model is None and s.pending(seed)]
    if len(todo) < 2:  # nothing to share the cores with: here, the kernel on every core
        return [simulation.run(seed) for simulation in simulations]
    with _kernel_workers(min(processes, len(todo))) as pool:
        futures = {k: pool.submit(simulations[k].run, seed) for k in todo}
        return [futures[k].result() if k in futures else simulation.run(seed)
                for k, simulation in enumerate(simulations)]  # fmt: skip


@contextlib.contextmanager
def _kernel_workers(processes: int) -> Iterator[cf.ProcessPoolExecutor]:
    """Worker processes for simulations, each kernel on one thread (forkserver: nothing of this process's
    threads is forked). On leaving, what is under way ends and what is queued is dropped (an error,
    Ctrl-C)."""
    pool = cf.ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("forkserver"),
                                  initializer=_one_kernel_thread)  # fmt: skip
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _one_kernel_thread() -> None:
    import numba

    numba.set_num_threads(1)


def prepare_experiment(
    experiment: str, overrides: dict | None = None, benches: int = 128, seed: int = 0, inverse_model=None,
    sessions_dir: Path | None = None,
) -> tuple[dict[str, RobotDescription], list[Plan], dict]:  # fmt: skip
    """An experiment's robots, plans and parameters, every one checked (parameters, size, duration, the
    robot's limits) before any session is written or any work starts. ``sessions_dir``: plans whose session
    is complete there are not checked against the robot's limits again (a complete session made otherwise is
    refused before anything runs, :func:`reusable`; the others passed these checks when they were run):
    ~7 s of a second main job's 17."""
    from acquisition.plans.experiments import expand_experiment

    robots, plans, params = expand_experiment(experiment, overrides, benches=benches, seed=seed)
    commands = params["commands"] if Path(experiment).stem == "experiment2" else ()
    learned = [m for m in ("hybrid", "history") if m in commands]
    if learned and inverse_model is None:
        raise ValueError(
            f"experiment2: {' and '.join(learned)} commands need a trained inverse model (train one first, "
            "or run without them: --set 'commands=[ik,static]')"
        )
    to_run = [p for p in plans if sessions_dir is None or _complete(sessions_dir / session_id(p)) is None]
    for name, robot in robots.items():  # every plan of every robot, before any session is written
        checker = SafetyChecker(robot)
        for p in to_run:
            if p.robot == name:
                checker.require_safe(p)
    return robots, plans, params
