"""The rig's lifecycle for a session: started in a process of its own, its ports awaited, its operator
controls (payloads, taps) and stopped in order; and the devices a session uses, a rig's or a port map's.

A rig started here runs ``python -m twin.rig`` in its own session (Ctrl-C reaches only us, who stop it in
order) and dies with us, even by SIGKILL. It simulates the very description it is given: an experiment's
variant of the robot (a link made rigid, joints fixed, the flange off) is what its plans expect, not the
robot of the same name. What cannot be done is a :class:`RigError` or the recorder setup's ``SetupError``,
one line each; nothing here prints.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from acquisition.errors import AcquisitionError
from acquisition.plans.plan import Plan
from acquisition.recorder.setup import SetupError, checked_ports, configured_ports, ports_file
from models.robot import RobotDescription
from twin.ptyhost import PORTS_FILE, send_control, wait_for_ports

log = logging.getLogger(__name__)

RIG_START_S = 60.0  # a rig publishes its ports within this (the twin's first compile included)
RUNNING_RIG_S = 10.0  # a rig already running elsewhere has published them, or publishes them within this


class RigError(AcquisitionError, RuntimeError):
    """A rig that cannot be started or found: its folder unwritable, stopped before publishing its ports,
    or no rig's ports where they were looked for."""


def rig_files(desc: RobotDescription, run_dir: Path, plan: Plan | None = None) -> list[str]:
    """The rig's description (and its bench's start, as ``plan`` starts) in ``run_dir``: its arguments."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "robot.yaml").write_text(desc.model_dump_json())  # JSON is YAML
    if plan is None:
        return []
    first = {"q_rad": plan.goal_q[:1], "pressure_pa": plan.pressure_pa[:1], "valve_open": plan.valve_open[:1]}
    (run_dir / "start.json").write_text(json.dumps({k: v[0].tolist() for k, v in first.items() if len(v)}))
    return ["--start", str(run_dir / "start.json")]


@contextlib.contextmanager
def rig_process(
    desc: RobotDescription, run_dir: Path, plan: Plan | None = None
) -> Iterator[subprocess.Popen]:
    """A rig of ``desc`` serving in ``run_dir`` for the block (its bench set up as ``plan`` starts: first
    pose, pressures and valves, as an operator sets it up), terminated after it (killed if it lingers)."""
    try:
        start = rig_files(desc, run_dir, plan)
    except OSError as exc:  # a read-only lab, a full disk: before anything was started
        raise RigError(f"cannot write the rig's folder {run_dir}: {exc.strerror or exc}") from exc
    proc = subprocess.Popen(
        [sys.executable, "-m", "twin.rig", "--robot", str(run_dir / "robot.yaml"),
         "--run-dir", str(run_dir), "--parent-pid", str(os.getpid()), *start], start_new_session=True,
    )  # fmt: skip
    log.debug("rig for %s started in %s (pid %d)", desc.name, run_dir, proc.pid)
    try:
        yield proc
    finally:
        log.debug("stopping the rig in %s", run_dir)
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def rig_ports(run_dir: Path, proc: subprocess.Popen | None = None) -> dict[str, str]:
    """The ports a rig published in ``run_dir``: the one ``proc`` runs (awaited while it starts), or one
    running elsewhere."""
    if proc is None and not (run_dir / PORTS_FILE).is_file():
        raise RigError(f"--ports {run_dir}: no {PORTS_FILE} in this folder (a rig's run directory has one; "
                       "is the rig running? `vslab rig`)")  # fmt: skip
    deadline = time.monotonic() + (RIG_START_S if proc is not None else RUNNING_RIG_S)
    while True:
        try:
            return wait_for_ports(run_dir, timeout_s=0.5)
        except TimeoutError:  # first: a TimeoutError is an OSError, and a rig that died must say so
            if proc is not None and proc.poll() is not None:
                raise RigError(f"the rig stopped (exit status {proc.returncode}) before it published its "
                               "ports") from None  # fmt: skip
            if time.monotonic() > deadline:
                running = "" if proc is not None else " (is the rig running? `vslab rig`)"
                raise RigError(f"no rig published its ports in {run_dir}{running}") from None
        except (ValueError, KeyError, OSError) as exc:  # a ports.json being replaced, or not the rig's
            if time.monotonic() > deadline:
                raise RigError(f"{run_dir / PORTS_FILE}: not a rig's ports file ({exc})") from None


def rig_controls(run_dir: Path) -> tuple[Callable[[float], object], Callable[[float], object]]:
    """(hang a payload of kg, tap the link with N·m·s) on the rig serving in ``run_dir``: the operator's
    hands, through its control socket."""
    return (lambda kg: send_control(run_dir, {"op": "payload", "kg": kg}),
            lambda nms: send_control(run_dir, {"op": "tap", "nms": nms}))  # fmt: skip


@contextlib.contextmanager
def session_devices(
    desc: RobotDescription, ports: Path | None = None, rig_dir: Path | None = None, plan: Plan | None = None
) -> Iterator[tuple[dict[str, str], Path | None]]:
    """(port map, rig run directory or None) for a session of ``desc``: a rig started in ``rig_dir`` for
    the block (stopped after it), or the devices ``ports`` names (a ports file, or a running rig's run
    directory), or the ports ``desc`` names. Every port is checked to be a serial port before anything opens
    it. SIGTERM becomes KeyboardInterrupt for the block, so both stop a session the same way."""
    if rig_dir is not None and ports is not None:  # a rig of its own has its own ports: another's is ignored
        raise SetupError(f"--ports {ports} with --rig: --rig starts a rig and uses its devices; give one of "
                         "them (a running rig's run directory is --ports DIR, without --rig)")  # fmt: skip
    with contextlib.ExitStack() as stack:
        proc = None if rig_dir is None else stack.enter_context(rig_process(desc, rig_dir, plan))
        previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
        stack.callback(signal.signal, signal.SIGTERM, previous)
        where = rig_dir if rig_dir is not None else ports
        if where is None:
            yield configured_ports(desc), None
        elif proc is not None or where.is_dir():
            yield checked_ports(desc, rig_ports(where, proc), f"{where / PORTS_FILE}"), where
        elif where.is_file():
            yield checked_ports(desc, ports_file(where), str(where)), None
        else:
            raise SetupError(f"--ports {where}: no ports file or rig directory there")
