"""`vslab record` and `vslab run`: hardware (or rig) sessions, recorded."""

from __future__ import annotations

import contextlib
import math
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from acquisition.errors import AcquisitionError
from vslab.app import (
    HISTORY_NOT_STORED,
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
    """``--rate servo_bus=1000`` → {"servo_bus": 1000.0}, each checked against the robot's devices, and
    every device's rate against what its link carries (``bus_budget.rate_refusal``)."""
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
    from acquisition.devices.bus_budget import rate_refusal

    for name in desc.devices:  # before the rig or any device is started: a rate the wire cannot carry
        if (refusal := rate_refusal(desc, name, out.get(name))) is not None:
            _error(refusal)
    return out


NO_INVERSE_MODEL = (
    "hybrid commands need a trained inverse model: --inverse-model VERSION (`vslab models list`)"
)


def _session_id(given: str | None, default: str) -> str:
    """``--session`` (or the default): a folder name under sessions/, checked before anything starts."""
    from acquisition.recorder.setup import SetupError, session_id

    try:
        return session_id(given, default)
    except SetupError as exc:
        _error(str(exc))


def _rig_dir(rig: bool, session_id: str) -> Path | None:
    """Where ``--rig`` starts the session's rig (None without it)."""
    return options().lab.rigs / session_id if rig else None


def _record_for(rec, duration: float) -> float:
    """Record with ``rec`` for ``duration`` s (0: until Ctrl-C), showing live counters; the seconds recorded.
    The duration counts from when every device has answered (connecting may take seconds); the live table
    goes when the recording stops, and the session's final account is printed in its place."""
    from rich.live import Live

    from acquisition.recorder.setup import recording

    with recording(rec), Live(console=console, refresh_per_second=2, transient=True) as counters:
        start = time.monotonic()
        earlier, earlier_s = rec.snapshot(), start
        try:
            while (duration <= 0 or time.monotonic() - start < duration) and rec.write_error is None:
                left = start + duration - time.monotonic() if duration > 0 else 0.5
                time.sleep(min(0.5, max(0.0, left)))
                if not options().quiet:
                    now, now_s = rec.snapshot(), time.monotonic()
                    counters.update(
                        _counter_table(now, now_s - start, earlier=earlier, window_s=now_s - earlier_s)
                    )
                    earlier, earlier_s = now, now_s
        except KeyboardInterrupt:
            pass
        return time.monotonic() - start


def _finish(rec) -> None:
    """The stopped recording's account: warnings for what was lost, one error line if it failed."""
    from acquisition.recorder.setup import recording_failure

    if rec.live_errors:
        console.print(f"[yellow]the live view failed {rec.live_errors} time(s); the file is complete[/]")
    if rec.write_error:
        _error(recording_failure(rec))
    lost = {t: c for t, c in (rec.final or {}).items() if c["lost"] or c["dropped"]}
    for topic, c in lost.items():
        console.print(f"[yellow]{topic}: {c['lost']:,} samples lost in {c['gaps']} gap(s), "
                      f"{c['dropped']:,} dropped[/]")  # fmt: skip
    for name, ms in rec.short_of_time().items():
        console.print(f"[yellow]{name} fell {ms:.0f} ms behind its schedule at worst (past 50 ms it skips "
                      "the polls it missed, counted lost): its reads fill most of each slot; record it at a "
                      "lower --rate[/]")  # fmt: skip
    for name, n in rec.restarts.items():
        console.print(f"[yellow]{name} was restarted {n} time(s) (see /events)[/]")
    for name, why in rec.silent.items():
        console.print(f"[red]{name} gave no sample:[/] {why}", soft_wrap=True, highlight=False)
    console.print(f"session {rec.session_id}: {', '.join(p.name for p in rec.parts)} in {rec.directory}")
    if failure := recording_failure(rec):
        _error(failure)


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
    from acquisition.recorder.recorder import Recorder
    from twin.rig_process import session_devices

    local_lab("record")
    desc = _robot(robot)
    rates = _rates(rate, desc)
    if not (duration >= 0 and math.isfinite(duration)):
        _error(f"--duration must be ≥ 0 s (0: until Ctrl-C), got {duration}")
    session_id = _session_id(session, time.strftime("%Y%m%d-%H%M%S") + f"-{desc.name}")
    try:
        with session_devices(desc, ports, _rig_dir(rig, session_id)) as (port_map, _):
            rec = Recorder(
                desc, port_map, options().lab.sessions.root / session_id, session_id, experiment, rates=rates
            )
            view = _live_view(desc, live_host, live_port) if live else contextlib.nullcontext()
            with view as live_server:
                rec.live = live_server
                recorded_s = _record_for(rec, duration)
    except AcquisitionError as exc:  # a port, the rig, the session folder, the recorder: one line
        _error(str(exc))
    if not options().quiet and rec.final is not None:
        console.print(_counter_table(_with_spans(rec), recorded_s, title=f"recorded {recorded_s:.1f} s"))
    _finish(rec)


def _with_spans(rec) -> dict:
    """The final account, each stream with its first and last written sample from the session's card."""
    from acquisition.schemas.session_files import SessionError, read_card

    try:
        written = read_card(rec.directory)["counters"]
    except (SessionError, KeyError):  # no card (the writer failed): the counts alone
        return rec.final
    spans = {t: {k: written.get(t, {}).get(k) for k in ("first_ns", "last_ns")} for t in rec.final}
    return {t: {**c, **spans[t]} for t, c in rec.final.items()}


@app.command()
def run(
    experiment: Annotated[str, typer.Argument(help="Experiment (configs/experiments/) or a YAML path.")],
    plan: Annotated[str, typer.Option(help="Which of its plans: a name, or its number (0 = first).")] = "0",
    set_: Annotated[list[str] | None, typer.Option("--set", help="Override a parameter: key=value.")] = None,
    ports: Annotated[Path | None, typer.Option(help=PORTS_HELP)] = None,
    rig: Annotated[bool, typer.Option("--rig", help=RIG_HELP)] = False,
    session: Annotated[str | None, typer.Option(help="Session id (default: time, plan).")] = None,
    inverse_model: Annotated[
        str | None, typer.Option(help="Saved inverse model for hybrid commands.")
    ] = None,
    rate: RateOption = None,
    live: LiveOption = False,
    live_host: LiveHost = "127.0.0.1",
    live_port: LivePort = 8765,
) -> None:
    """Run one plan of an experiment in real time on the devices (or the rig) while recording it. Payload
    changes and taps prompt the operator (on the rig: applied). Ctrl-C: a safe stop; the file stays valid."""
    from acquisition.plans.plan_run import (
        choose_plan,
        operator_prompts,
        plan_session,
        ready_plan,
        record_plan,
    )
    from acquisition.recorder.recorder import Recorder
    from twin.rig_process import rig_controls, session_devices

    local_lab("run")
    overrides = _overrides(set_ or [])
    model = None if inverse_model is None else load_inverse_model(inverse_model)  # checked, whatever the plan
    refused = {"history": HISTORY_NOT_STORED} | ({"hybrid": NO_INVERSE_MODEL} if model is None else {})
    try:
        the_plan, desc = choose_plan(experiment, plan, overrides)
        device_rates = _rates(rate, desc)
        learned = None
        if model is not None:  # torch and the baselines load only for a learned command (seconds)
            from pipeline.in_loop import learned_compensators

            learned = learned_compensators({"hybrid": model}, desc)
        compensator = ready_plan(the_plan, desc, learned, refused)
        session_id = _session_id(session, time.strftime("%Y%m%d-%H%M%S-") + the_plan.name.replace("/", "-"))
        console.print(f"{the_plan.name}: {the_plan.duration_s:.1f} s on {desc.name}")
        with session_devices(desc, ports, _rig_dir(rig, session_id), the_plan) as (port_map, rig_dir):
            controls = rig_controls(rig_dir) if rig else operator_prompts(_prompt)
            view = (lambda: _live_view(desc, live_host, live_port)) if live else None
            rec = Recorder(desc, port_map, options().lab.sessions.root / session_id, session_id,
                           rates=device_rates, **plan_session(the_plan, experiment))  # fmt: skip
            report = record_plan(the_plan, rec, compensator, controls, view)
    except AcquisitionError as exc:  # PlanRunError, a port, the rig, the session folder: nothing started
        _error(str(exc))
    _finish(rec)
    at = f"{report.elapsed_s:.1f} s of {the_plan.duration_s:.1f} s"
    if report.status != "complete":  # the session is kept (valid up to the stop); the job is not done
        why = escape(report.reason)
        console.print(f"[yellow]{report.status}[/] at {at}: {why} (the session is kept up to the stop; its "
                      "events say why)", soft_wrap=True, highlight=False)  # fmt: skip
        raise typer.Exit(code=130 if report.status == "interrupted" else 1)
    console.print(f"[green]complete[/] at {at}")


def _prompt(text: str) -> None:
    """Ask the operator to do ``text``; the plan's clock waits for Enter."""
    typer.prompt(text, default="", show_default=False)


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


def _counter_table(snapshot: dict, elapsed: float, title: str = "", earlier: dict | None = None,
                   window_s: float = 0.0) -> Table:  # fmt: skip
    """The streams' accounts. The rate is each stream's own: over its first to last written sample in a
    final account (streams start when their device first answers, seconds apart), else over the last
    ``window_s`` (``earlier``: the snapshot then)."""
    table = Table("topic", "expected", "received", "lost", "written", "dropped", "rate Hz",
                  title=title or f"recording {elapsed:.0f} s")  # fmt: skip
    for topic, c in sorted(snapshot.items()):
        rate = _stream_rate(c, (earlier or {}).get(topic), window_s)
        counts = [f"{c[k]:,}" for k in ("expected", "received", "lost", "written", "dropped")]
        table.add_row(topic, *counts, f"{rate:.0f}")
    return table


def _stream_rate(c: dict, earlier: dict | None, window_s: float) -> float:
    """Samples per second of one stream: written over its own span, or received over the window."""
    if c.get("first_ns") is not None and c.get("last_ns") is not None and c["last_ns"] > c["first_ns"]:
        return (c["written"] - 1) / ((c["last_ns"] - c["first_ns"]) / 1e9)
    if earlier is not None and window_s > 0:
        return (c["received"] - earlier["received"]) / window_s
    return 0.0
