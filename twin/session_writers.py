"""The sessions of a simulated batch being written (the simulated-time runner's writing half): the runner
hands over each stepped window (``twin.stepping.Window``: a few arrays for every bench) and each session's
messages are cut from it (``write_window``), gathered over ``write_s`` of simulated time and written.

Measured and not kept: writing in a forked process beside the stepping (the windows over a pipe). On two
cores it was no faster (16–20 s against 16 s for a quarter campaign): the twin's kernel runs on both cores,
and a busy second process stalls its parallel regions.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.plans.plan import Plan
from acquisition.recorder.writer import SessionWriter
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.topics import session_topics
from models.robot import RobotDescription
from twin.buffered_writer import BufferedSessionWriter
from twin.stepping import Window

SIM_EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: simulated sessions start here on the host clock


@dataclass(frozen=True)
class SessionSpec:
    """One session of a batch: where it goes, its id and experiment, its metadata, and its start event's
    (label, log time in ns)."""

    directory: Path
    session_id: str
    experiment: str
    metadata: dict
    start: tuple[str, int]


class BatchWriters:
    """Every session of a batch: ``write_window`` after each stepped window, ``end`` at the end (each
    session's writes gathered over ``write_s``, its chunks compressed in threads beside the loop). The
    writers' clock is the simulated one, so a session's bytes never depend on how fast the machine ran."""

    def __init__(self, robot: RobotDescription, plans: list[Plan], specs: list[SessionSpec],
                 write_s: float) -> None:  # fmt: skip
        self.plans = plans
        self.topics = session_topics(robot)
        self.servo_joints = [i for i, j in enumerate(robot.joints) if j.drive != "stepper"]
        self.event_t = [np.array([t for t, _ in p.events]) for p in plans]
        self.last_goal = np.full(len(plans), -1)  # each bench's latest goal and pressure set-point written
        self.last_pressure = np.full(len(plans), -1)
        self.messages = 0
        self.now_s = 0.0
        self._compress = ThreadPoolExecutor(os.cpu_count() or 1, thread_name_prefix="compress")
        self.sessions: list[BufferedSessionWriter] = []
        try:
            for spec in specs:
                if spec.directory.exists():  # an incomplete earlier try: start it again
                    for old in spec.directory.glob("*"):
                        old.unlink()
                w = SessionWriter(spec.directory, robot, spec.session_id, experiment=spec.experiment,
                                  metadata=spec.metadata, flush_s=30.0, clock=lambda: self.now_s,
                                  standard_batch_s=write_s, compress_in=self._compress)  # fmt: skip
                w.open()
                w.event(Event(EventKind.SESSION_START, label=spec.start[0]), spec.start[1])
                self.sessions.append(BufferedSessionWriter(w, write_s))
        except BaseException:
            self._compress.shutdown(cancel_futures=True)
            raise

    def write_window(self, window: Window) -> None:
        """Every bench's messages of a stepped window."""
        for r, w in enumerate(self.sessions):
            self.messages += write_window(w, self.topics, window, r, self.plans[r], self.event_t[r],
                                          self.last_goal, self.last_pressure, self.servo_joints)  # fmt: skip
        self.now_s = window.t1
        for w in self.sessions:
            w.flush_if_due(window.t1)

    def end(self, durations: np.ndarray, finished: bool) -> int:
        """End the sessions: each one's SESSION_END where the run finished, and close them (refused at
        t = 0: nothing of the plan ran; a run stopped part-way, by an interrupt or a failed write, completes
        none of them, so the next runs them again). Returns the messages written."""
        try:
            if finished:
                for w, p, d in zip(self.sessions, self.plans, durations, strict=True):
                    w.event(Event(EventKind.SESSION_END, label=p.name), SIM_EPOCH_NS + round(d * 1e9))
        finally:
            self.close([("refused" if d <= 0 else "complete") if finished else "interrupted"
                        for d in durations])  # fmt: skip
        return self.messages

    def close(self, statuses: list[str]) -> None:
        """Close every session with its status (``SessionWriter.close``); the first failure is raised once
        all are closed."""
        failure = None
        try:
            for w, status in zip(self.sessions, statuses, strict=True):
                try:
                    w.close(status)
                except Exception as exc:  # the others still close
                    failure = failure or exc
        finally:
            self._compress.shutdown(cancel_futures=True)
        if failure is not None:
            raise failure


def write_window(w: BufferedSessionWriter, topics: dict, window: Window, r: int, plan: Plan,
                  event_t: np.ndarray, last_goal: np.ndarray, last_pressure: np.ndarray,
                  servo_joints: list[int]) -> int:  # fmt: skip
    """Bench ``r``'s messages of a stepped window: its commands, device rows and events, nothing after its
    session's end; returns how many."""
    t0, t1, stops, refused, end = window.t0, window.t1, window.stops, window.refused, window.durations[r]
    if t0 >= end and r not in stops:  # a stop at t = 0 still writes its events
        return 0
    messages = _write_commands(
        w, topics, window.commands, window.tb, last_goal, last_pressure, r, servo_joints
    )
    for topic, (robot_idx, host_ns, topic_rows) in window.rows.items():
        lo, hi = np.searchsorted(robot_idx, [r, r + 1])
        sel = slice(lo, hi)
        if t1 > end:  # the plan ends in this window: nothing after its end
            sel = lo + np.flatnonzero(host_ns[lo:hi] <= end * 1e9)
        w.write(topic, SIM_EPOCH_NS + host_ns[sel], topic_rows[sel])
        messages += len(topic_rows[sel])
    e_lo = np.searchsorted(event_t, t0, side="left")
    e_hi = np.searchsorted(event_t, min(t1, end), "right" if t1 >= end else "left")
    for t_event, event in plan.events[e_lo:e_hi]:
        w.event(event, SIM_EPOCH_NS + round(t_event * 1e9))
        messages += 1
    if r in refused and stops.get(r) == refused[r]:
        w.event(Event(EventKind.COMMAND_REFUSED, label="compensator", text=refused[r][1].text),
                SIM_EPOCH_NS + round(refused[r][0] * 1e9))  # fmt: skip
        messages += 1
    if r in stops:
        w.event(stops[r][1], SIM_EPOCH_NS + round(stops[r][0] * 1e9))
        messages += 1
    return messages


def _write_commands(w: BufferedSessionWriter, topics, commands: dict, tb: np.ndarray, last_goal,
                    last_pressure, r: int, servo_joints: list[int]) -> int:  # fmt: skip
    """Bench ``r``'s servo goals and pressure commands at the blocks where its plan changed them."""
    n = 0
    cmds = {k: v[:, r] for k, v in commands.items()}
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
