"""`vslab record` and `vslab run`: hardware (or rig) sessions, recorded."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from pipeline.lab import Lab
from vslab.app import (
    HISTORY_NOT_REGISTERED,
    CommandLineError,
    _error,
    _overrides,
    _robot,
    app,
    console,
    load_inverse_model,
    local_lab,
    options,
)

PORTS_HELP = "ports.json (or the rig's run directory) naming each device's port."
RIG_HELP = "Start a rig (the twin behind emulators) and use its devices."
LiveOption = Annotated[bool, typer.Option("--live", help="Serve the streams to Foxglove over WebSocket.")]
LiveHost = Annotated[str, typer.Option(help="Address the live view binds to.")]
LivePort = Annotated[int, typer.Option(help="Port of the live view (0: any free one).")]
RateOption = Annotated[
    list[str] | None,
    typer.Option("--rate", help="A device's rate over the robot description's: DEVICE=HZ (repeatable)."),
]


def _rates(pairs: list[str] | None, desc) -> dict[str, float]:
    """``--rate servo_bus=1000`` → {"servo_bus": 1000.0}, each checked against the robot's devices."""
    out = {}
    for pair in pairs or []:
        name, sep, value = pair.partition("=")
        name = name.strip()
        try:
            hz = float(value)
        except ValueError:
            hz = float("nan")
        if not sep or not hz > 0 or hz == float("inf"):
            _error(f"--rate takes DEVICE=HZ with a positive rate, got {pair!r}")
        if name not in desc.devices:
            _error(
                f"--rate {pair}: {desc.name} has no device {name!r} (its devices: {', '.join(desc.devices)})"
            )
        out[name] = hz
    return out


SESSION_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
RIG_START_S = 60.0  # a rig publishes its ports within this (the twin's first compile included)


def _session_id(given: str | None, default: str) -> str:
    """``--session`` (or the default): a folder name under sessions/, checked before anything starts."""
    sid = default if given is None else given
    if not SESSION_ID.fullmatch(sid):
        _error(f"--session {sid!r}: a session id is a folder name: letters, digits, '.', '_' and '-' (at "
               "most 128, not starting with '.' or '-')")  # fmt: skip
    return sid


@contextlib.contextmanager
def _devices(desc, ports: Path | None, rig: bool, session_id: str, plan=None, lab: Lab | None = None):
    """(port map, rig run directory or None): the devices named by ``ports``, or a rig started for the
    session (stopped on exit), its bench set up as ``plan`` starts (first pose, pressures and valves) as an
    operator sets it up. Every port is checked to be a serial port before anything opens it. SIGTERM
    becomes KeyboardInterrupt, so both stop a session the same way."""
    rig_proc = None
    if rig and ports is not None:  # a rig of its own has its own ports: another's would be ignored
        _error(f"--ports {ports} with --rig: --rig starts a rig and uses its devices; give one of them "
               "(a running rig's run directory is --ports DIR, without --rig)")  # fmt: skip
    if rig:
        ports = (lab or options().lab).rigs / session_id
        # the rig simulates this very description: an experiment's variant of the robot (a link made rigid,
        # joints fixed, the flange off) is what its plans expect, not the robot of the same name
        try:
            start = _rig_files(desc, ports, plan)
        except OSError as exc:  # a read-only lab, a full disk: before anything was started
            _error(f"cannot write the rig's folder {ports}: {exc.strerror or exc}")
        # its own session (Ctrl-C reaches only us, who stop it in order); it dies with us, even by SIGKILL
        rig_proc = subprocess.Popen(
            [sys.executable, "-m", "twin.rig", "--robot", str(ports / "robot.yaml"),
             "--run-dir", str(ports), "--parent-pid", str(os.getpid()), *start], start_new_session=True,
        )  # fmt: skip
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        if ports is None:
            configured = {n: d.port for n, d in desc.devices.items() if d.port != "auto"}
            if not configured:
                _error(f"say where the devices are: --ports <ports.json | rig run dir>, --rig, or a port for "
                       f"each device in {desc.name}'s description (devices.<name>.port)")  # fmt: skip
            yield _checked_ports(desc, configured, f"{desc.name}'s description (devices.<name>.port)"), None
        elif rig or ports.is_dir():
            yield _checked_ports(desc, _rig_ports(ports, rig_proc), f"{ports / 'ports.json'}"), ports
        elif ports.is_file():
            yield _checked_ports(desc, _ports_file(ports), str(ports)), None
        else:
            _error(f"--ports {ports}: no ports file or rig directory there")
    finally:
        signal.signal(signal.SIGTERM, previous)
        if rig_proc is not None:
            rig_proc.terminate()
            try:
                rig_proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                rig_proc.kill()
                rig_proc.wait()


def _rig_files(desc, run_dir: Path, plan) -> list[str]:
    """The rig's description (and its bench's start, as ``plan`` starts) in ``run_dir``: its arguments."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "robot.yaml").write_text(desc.model_dump_json())  # JSON is YAML
    if plan is None:
        return []
    first = {"q_rad": plan.goal_q[:1], "pressure_pa": plan.pressure_pa[:1], "valve_open": plan.valve_open[:1]}
    (run_dir / "start.json").write_text(json.dumps({k: v[0].tolist() for k, v in first.items() if len(v)}))
    return ["--start", str(run_dir / "start.json")]


def _rig_ports(run_dir: Path, rig_proc: subprocess.Popen | None) -> dict[str, str]:
    """The ports a rig published in ``run_dir`` (the one we started, or one running elsewhere)."""
    from twin.ptyhost import PORTS_FILE, wait_for_ports

    if rig_proc is None and not (run_dir / PORTS_FILE).is_file():
        _error(f"--ports {run_dir}: no {PORTS_FILE} in this folder (a rig's run directory has one; is the "
               "rig running? `vslab rig`)")  # fmt: skip
    deadline = time.monotonic() + (RIG_START_S if rig_proc is not None else 10.0)
    while True:
        try:
            return wait_for_ports(run_dir, timeout_s=0.5)
        except (ValueError, KeyError, OSError) as exc:  # a ports.json being replaced, or not the rig's
            if time.monotonic() > deadline:
                _error(f"{run_dir / PORTS_FILE}: not a rig's ports file ({exc})")
        except TimeoutError:
            if rig_proc is not None and rig_proc.poll() is not None:
                _error(f"the rig stopped (exit status {rig_proc.returncode}) before it published its ports")
            if time.monotonic() > deadline:
                running = "" if rig_proc is not None else " (is the rig running? `vslab rig`)"
                _error(f"no rig published its ports in {run_dir}{running}")


def _ports_file(path: Path) -> dict[str, str]:
    """A ports file: a JSON object of device name → port path (or a rig's ``{"ports": {...}}``)."""
    try:
        port_map = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError) as exc:  # not JSON, not UTF-8, unreadable
        _error(f"--ports {path}: not a ports file ({getattr(exc, 'strerror', None) or exc})")
    port_map = port_map.get("ports", port_map) if isinstance(port_map, dict) else None
    if not isinstance(port_map, dict) or not all(isinstance(v, str) and v for v in port_map.values()):
        _error(f"--ports {path}: expected a JSON object of device name → port path, like "
               '{"servo_bus": "/dev/ttyUSB0"}')  # fmt: skip
    return port_map


def _checked_ports(desc, port_map: dict[str, str], source: str) -> dict[str, str]:
    """``port_map`` once every entry names a device of ``desc`` and a serial port this user may open (it is
    not opened here: opening an Arduino's port resets it); one error line naming the device otherwise."""
    if foreign := sorted(set(port_map) - set(desc.devices)):
        _error(f"{source}: {', '.join(foreign)}: {desc.name} has no such device (its devices: "
               f"{', '.join(desc.devices)}; the ports of another robot?)")  # fmt: skip
    for name, port in port_map.items():
        if problem := _not_a_serial_port(port):
            _error(f"{source}: {name}: {port}: {problem}")
    return port_map


def _not_a_serial_port(port: str) -> str | None:
    """Why ``port`` is not a serial port this user may open (None if it may be one): missing, not a character
    device, a device of another kind (Linux names each device's kind in /sys/dev/char), no permission."""
    try:
        st = os.stat(port)
    except FileNotFoundError:
        return "no such port (is the device plugged in? its name may have changed: ls /dev/serial/by-id/)"
    except (OSError, ValueError) as exc:
        return f"cannot be checked ({getattr(exc, 'strerror', None) or exc})"
    if stat.S_ISDIR(st.st_mode):
        return "a folder, not a serial port"
    if not stat.S_ISCHR(st.st_mode):
        return "a regular file, not a serial port" if stat.S_ISREG(st.st_mode) else "not a serial port"
    kind = Path(f"/sys/dev/char/{os.major(st.st_rdev)}:{os.minor(st.st_rdev)}/subsystem")
    if kind.exists() and kind.resolve().name != "tty":
        return f"a {kind.resolve().name} device, not a serial port"
    if not os.access(port, os.R_OK | os.W_OK):
        return "no permission to open it (on Linux: add the user to the dialout group, then log in again)"
    return None


def _recorder(desc, port_map: dict, session_id: str, experiment: str, rates: dict, live: bool, host: str,
              port: int, lab: Lab | None = None, **meta):  # fmt: skip
    """The session's Recorder (not started) and its live view (or a null context)."""
    from acquisition.recorder.recorder import Recorder, RecorderError

    directory = (lab or options().lab).sessions.path(session_id)
    if directory.exists() and any(directory.glob("*.mcap")):
        _error(f"session {session_id} exists already in {directory.parent}: choose another --session")
    try:
        rec = Recorder(desc, port_map, directory, session_id, experiment=experiment, rates=rates,
                       metadata=meta)  # fmt: skip
    except RecorderError as exc:
        _error(str(exc))
    if not rec.devices:
        _error(f"none of {desc.name}'s devices ({', '.join(desc.devices)}) is in the port map "
               f"({', '.join(port_map) or 'empty'})")  # fmt: skip
    view = _live_view(desc, host, port) if live else contextlib.nullcontext()
    return rec, view


@contextlib.contextmanager
def _recording(rec):
    """``with rec``, with a recorder that cannot start reported as one line."""
    from acquisition.recorder.recorder import RecorderError

    try:
        rec.start()
    except (RecorderError, OSError) as exc:  # OSError: the sessions folder cannot be written
        _error(str(exc))
    try:
        yield rec
    finally:
        rec.stop()


def _finish(rec) -> None:
    if rec.live_errors:
        console.print(f"[yellow]the live view failed {rec.live_errors} time(s); the file is complete[/]")
    if rec.write_error:
        _error(f"the session writer failed: {rec.write_error}")
    lost = {t: c for t, c in (rec.final or {}).items() if c["lost"] or c["dropped"]}
    for topic, c in lost.items():
        console.print(f"[yellow]{topic}: {c['lost']:,} samples lost in {c['gaps']} gap(s), "
                      f"{c['dropped']:,} dropped[/]")  # fmt: skip
    for name, n in rec.restarts.items():
        console.print(f"[yellow]{name} was restarted {n} time(s) (see /events)[/]")
    for name, why in rec.silent.items():
        console.print(f"[red]{name} gave no sample:[/] {why}", soft_wrap=True, highlight=False)
    console.print(f"session {rec.session_id}: {', '.join(p.name for p in rec.parts)} in {rec.directory}")
    if rec.silent and len(rec.silent) == len(rec.devices):
        _error("no device gave a sample: check the ports (`--ports`, or devices.<name>.port)")


@app.command()
def record(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    ports: Annotated[Path | None, typer.Option(help=PORTS_HELP)] = None,
    rig: Annotated[bool, typer.Option("--rig", help=RIG_HELP)] = False,
    duration: Annotated[float, typer.Option(help="Seconds to record (0: until Ctrl-C).")] = 0.0,
    session: Annotated[str | None, typer.Option(help="Session id (default: time, robot).")] = None,
    experiment: Annotated[
        str, typer.Option(help="What this session is (stored in its metadata).")
    ] = "manual",
    rate: RateOption = None,
    live: LiveOption = False,
    live_host: LiveHost = "127.0.0.1",
    live_port: LivePort = 8765,
) -> None:
    """Record every device of a robot to one MCAP session, with live counters; Ctrl-C stops cleanly."""
    from rich.live import Live

    local_lab("record")
    desc = _robot(robot)
    rates = _rates(rate, desc)
    if not (duration >= 0 and math.isfinite(duration)):
        _error(f"--duration must be ≥ 0 s (0: until Ctrl-C), got {duration}")
    session_id = _session_id(session, time.strftime("%Y%m%d-%H%M%S") + f"-{desc.name}")
    with _devices(desc, ports, rig, session_id) as (port_map, _):
        rec, view = _recorder(desc, port_map, session_id, experiment, rates, live, live_host, live_port)
        with view as live_server:
            rec.live = live_server
            # the duration counts from when every device has answered (connecting may take seconds); the live
            # table goes when the recording stops, and the session's final account is printed in its place
            with _recording(rec), Live(console=console, refresh_per_second=2, transient=True) as counters:
                start = time.monotonic()
                try:
                    while (duration <= 0 or time.monotonic() - start < duration) and rec.write_error is None:
                        left = start + duration - time.monotonic() if duration > 0 else 0.5
                        time.sleep(min(0.5, max(0.0, left)))
                        if not options().quiet:
                            counters.update(_counter_table(rec.snapshot(), time.monotonic() - start))
                except KeyboardInterrupt:
                    pass
                recorded_s = time.monotonic() - start
    if not options().quiet and rec.final is not None:
        console.print(_counter_table(rec.final, recorded_s, title=f"recorded {recorded_s:.1f} s"))
    _finish(rec)


@app.command()
def run(
    experiment: Annotated[str, typer.Argument(help="Experiment (configs/experiments/) or a YAML path.")],
    plan: Annotated[str, typer.Option(help="Which of its plans: a name, or its number (0 = first).")] = "0",
    set_: Annotated[list[str] | None, typer.Option("--set", help="Override a parameter: key=value.")] = None,
    ports: Annotated[Path | None, typer.Option(help=PORTS_HELP)] = None,
    rig: Annotated[bool, typer.Option("--rig", help=RIG_HELP)] = False,
    session: Annotated[str | None, typer.Option(help="Session id (default: time, plan).")] = None,
    inverse_model: Annotated[
        str | None, typer.Option(help="Registered inverse model for hybrid commands.")
    ] = None,
    rate: RateOption = None,
    live: LiveOption = False,
    live_host: LiveHost = "127.0.0.1",
    live_port: LivePort = 8765,
) -> None:
    """Run one plan of an experiment in real time on the devices (or the rig) while recording it. Payload
    changes and taps prompt the operator (on the rig: applied). Ctrl-C: a safe stop; the file stays valid."""
    local_lab("run")
    try:
        the_plan, report = run_plan(experiment, plan, _overrides(set_ or []), ports=ports, rig=rig,
                                    session=session, inverse_model=inverse_model, rates=rate, live=live,
                                    live_host=live_host, live_port=live_port)  # fmt: skip
    except PlanRunError as exc:
        _error(str(exc))
    at = f"{report.elapsed_s:.1f} s of {the_plan.duration_s:.1f} s"
    if report.status != "complete":  # the session is kept (valid up to the stop); the job is not done
        why = escape(report.reason)
        console.print(f"[yellow]{report.status}[/] at {at}: {why} (the session is kept up to the stop; its "
                      "events say why)", soft_wrap=True, highlight=False)  # fmt: skip
        raise typer.Exit(code=130 if report.status == "interrupted" else 1)
    console.print(f"[green]complete[/] at {at}")


class PlanRunError(CommandLineError):
    """A plan that cannot be run as asked (unknown plan, unsafe, no model for hybrid commands, a runner's
    stop on an error): nothing was started, or the session was stopped safely and kept."""


def run_plan(experiment: str, plan: str = "0", overrides: dict | None = None, *, ports: Path | None = None,
             rig: bool = False, session: str | None = None, inverse_model: str | None = None,
             rates: list[str] | None = None, live: bool = False, live_host: str = "127.0.0.1",
             live_port: int = 8765, say=console.print, lab: Lab | None = None):  # fmt: skip
    """One plan of ``experiment`` (by name or number) run in real time on the devices named by ``ports`` (or
    on a rig started for it) while recording it: ``(plan, RunReport)``. The library form of `vslab run`
    (the main job calls it, with its ``lab``; the CLI's by default); what cannot be run is a
    :class:`PlanRunError`, checked before anything starts."""
    from acquisition.plans.compensation import StaticModelCompensator
    from acquisition.plans.experiments import expand_experiment
    from acquisition.plans.rt_runner import RealTimeRunner, RunnerError
    from acquisition.safety import SafetyChecker, SafetyError
    from pipeline.in_loop import InverseModelCompensator

    models = None if lab is None else lab.models
    model = None if inverse_model is None else load_inverse_model(inverse_model, models)  # whatever the plan
    try:
        robots, plans, _ = expand_experiment(experiment, overrides)
    except (ValueError, OSError) as exc:  # ExperimentError, RobotDescriptionError, an unreachable path
        raise PlanRunError(str(exc)) from None
    chosen = [p for k, p in enumerate(plans) if plan in (p.name, str(k))]
    if not chosen:
        more = " …" if len(plans) > 10 else ""
        raise PlanRunError(f"{experiment} has no plan {plan!r}; its plans (or their numbers, from 0): "
                           + ", ".join(p.name for p in plans[:10]) + more)  # fmt: skip
    the_plan = chosen[0]
    desc = robots[the_plan.robot]
    device_rates = _rates(rates, desc)
    try:  # before any device is opened, the rig started or the session folder made
        SafetyChecker(desc).require_safe(the_plan)
    except SafetyError as exc:
        first, _, details = str(exc).partition("\n")
        raise PlanRunError(f"{first.rstrip(':')}: refused, nothing was started:\n{details}") from None
    commands = the_plan.parameters.get("commands", "ik")
    compensator = None
    if commands == "static":
        compensator = StaticModelCompensator(desc, the_plan.parameters["payload_kg"])
    elif commands == "hybrid":
        if model is None:
            raise PlanRunError(
                "hybrid commands need a trained inverse model: --inverse-model VERSION (`vslab models list`)"
            )
        compensator = InverseModelCompensator(model, desc)
    elif commands == "history":
        raise PlanRunError(HISTORY_NOT_REGISTERED)
    session_id = _session_id(session, time.strftime("%Y%m%d-%H%M%S-") + the_plan.name.replace("/", "-"))
    say(f"{the_plan.name}: {the_plan.duration_s:.1f} s on {desc.name}")
    with _devices(desc, ports, rig, session_id, the_plan, lab) as (port_map, rig_dir):
        on_payload, on_tap = _operator(rig_dir if rig else None)
        name = the_plan.parameters.get("experiment", experiment)
        rec, view = _recorder(desc, port_map, session_id, name, device_rates, live, live_host, live_port,
                              lab=lab, plan=the_plan.name, runner="real-time",
                              parameters=the_plan.parameters)  # fmt: skip
        with view as live_server:
            rec.live = live_server
            with _recording(rec):
                try:
                    report = RealTimeRunner(rec, the_plan, compensator, on_payload, on_tap).run()
                except (SafetyError, RunnerError) as exc:
                    raise PlanRunError(str(exc)) from None
    _finish(rec)
    return the_plan, report


def _operator(rig_dir: Path | None):
    """Who hangs payloads and taps the link: the rig (through its control socket) or the operator (prompted;
    the plan's clock waits for Enter)."""
    from twin.ptyhost import send_control

    if rig_dir is not None:
        return (lambda kg: send_control(rig_dir, {"op": "payload", "kg": kg}),
                lambda nms: send_control(rig_dir, {"op": "tap", "nms": nms}))  # fmt: skip

    def payload(kg: float) -> None:
        typer.prompt(
            f"hang {kg * 1e3:g} g at the end-effector, then press Enter", default="", show_default=False
        )

    def tap(nms: float) -> None:
        typer.prompt(
            f"tap the link (≈ {nms * 1e3:g} mN·m·s), then press Enter", default="", show_default=False
        )

    return payload, tap


def _live_view(desc, host: str, port: int):
    """A started Foxglove live view of ``desc``'s topics; tells the user where to point Foxglove."""
    import ipaddress

    from acquisition.recorder.live import LiveServer
    from acquisition.schemas.scene import Scene
    from acquisition.schemas.topics import session_topics

    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        console.print(f"[yellow]warning: the live view on {host} is unauthenticated: anyone who can reach "
                      f"it sees the streams[/]")  # fmt: skip
    try:
        server = LiveServer(session_topics(desc), host=host, port=port, scene=Scene(desc)).start()
    except Exception as exc:  # a port in use, an address not ours
        _error(f"cannot start the live view on {host}:{port}: {exc}")
    console.print(f"live view: open {server.url} in Foxglove (Open connection → Foxglove WebSocket)")
    return server


def _counter_table(snapshot: dict, elapsed: float, title: str = "") -> Table:
    table = Table("topic", "expected", "received", "lost", "written", "dropped", "rate Hz",
                  title=title or f"recording {elapsed:.0f} s")  # fmt: skip
    for topic, c in sorted(snapshot.items()):
        rate = c["received"] / elapsed if elapsed > 0 else 0.0
        counts = [f"{c[k]:,}" for k in ("expected", "received", "lost", "written", "dropped")]
        table.add_row(topic, *counts, f"{rate:.0f}")
    return table
