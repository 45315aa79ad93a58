"""The `vslab` command: wiring only — parse options, call the packages, show results."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from models.robot import CONFIG_DIR, RobotDescriptionError, load_robot

app = typer.Typer(
    help="vslab: log, train and plot for soft variable-stiffness-link robots.", no_args_is_help=True
)
robots_app = typer.Typer(help="Robot descriptions in configs/robots/.", no_args_is_help=True)
twin_app = typer.Typer(help="The digital twin.", no_args_is_help=True)
app.add_typer(robots_app, name="robots")
app.add_typer(twin_app, name="twin")
sessions_app = typer.Typer(help="Recorded sessions in <lab>/sessions/.", no_args_is_help=True)
app.add_typer(sessions_app, name="sessions")

console = Console()


class Settings:
    """Options every command shares (set by the top-level callback)."""

    lab: Path = Path("lab")
    quiet: bool = False


@app.callback()
def main(
    lab: Annotated[
        Path, typer.Option(help="Lab directory (sessions, datasets, models, figures).", envvar="VSLAB_LAB")
    ] = Path("lab"),
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
) -> None:
    """Options shared by every command."""
    Settings.lab = lab
    Settings.quiet = quiet
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(levelname)s %(message)s")


def _fail(message: str) -> None:
    console.print(f"[red]error:[/red] {message}", soft_wrap=True, highlight=False)
    raise typer.Exit(code=2)


def _robot(name: str):
    try:
        return load_robot(name)
    except RobotDescriptionError as exc:
        _fail(str(exc))


@robots_app.command("list")
def robots_list() -> None:
    """List the robot descriptions shipped in configs/robots/."""
    table = Table("name", "description", "actuated", "virtual joints")
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        robot = _robot(str(path))
        table.add_row(
            robot.name, robot.description, " ".join(robot.actuated_joints), " ".join(robot.virtual_joints)
        )
    console.print(table)


@robots_app.command("show")
def robots_show(name: Annotated[str, typer.Argument(help="Robot name or path to a YAML file.")]) -> None:
    """Validate a robot description and print it as JSON (SI units)."""
    robot = _robot(name)
    console.print_json(robot.model_dump_json())


@twin_app.command("survey")
def twin_survey(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    trajectory: Annotated[
        str, typer.Option(help="Experiment 1 trajectory: linear, curve or square.")
    ] = "curve",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Experiment 1 on the twin: mean tip error (mm) per pressure × payload."""
    from acquisition.sim.survey import experiment1_survey

    desc = _robot(robot)
    try:
        grid = experiment1_survey(desc, trajectory=trajectory, seed=seed)
    except ValueError as exc:
        _fail(str(exc))
    _print_grid(grid, f"{desc.name}: mean tip error (mm), true tip vs rigid FK of the encoders, {trajectory}")
    out = Settings.lab / "twin" / f"survey_{desc.name}_{trajectory}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(grid.to_dict(), indent=2))
    if not Settings.quiet:
        console.print(f"written: {out}")


@app.command()
def rig(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    run_dir: Annotated[Path | None, typer.Option(help="Where ports.json and the port links go.")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Run the twin in real time behind emulators of the robot's devices (until Ctrl-C / SIGTERM)."""
    from acquisition.sim.rig import serve_rig

    desc = _robot(robot)
    where = run_dir or Settings.lab / "rig"
    if not Settings.quiet:
        console.print(f"rig for {desc.name}: ports in {where / 'ports.json'} (Ctrl-C stops)")
    serve_rig(desc, where, seed=seed)


@app.command()
def demo(seed: Annotated[int, typer.Option(help="Random seed.")] = 0) -> None:
    """The main job, end to end on the twin (grows with the pipeline, training and figures)."""
    from acquisition.sim.survey import PRESSURES_BAR, experiment1_survey, popup_reach_check

    Settings.lab.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, pressures in (("vsl", PRESSURES_BAR), ("vsl_rigid", (2.0,))):  # rigid links: pressure n/a
        grid = experiment1_survey(_robot(name), trajectory="curve", pressures_bar=pressures, seed=seed)
        _print_grid(grid, f"{name}: mean tip error (mm) on the curve, true tip vs rigid FK of the encoders")
        results[name] = grid.to_dict()
    popup = popup_reach_check(_robot("popup"), seed=seed)
    console.print(
        f"popup: tip deflection (PRBM − RBM) under 2 kg at 60 kPa, q0 = [0, 60, −120]°: "
        f"{popup['deflection_mm']:.1f} mm (paper: 6.6 mm; our link masses are assumed)"
    )
    results["popup"] = popup
    out = Settings.lab / "twin" / "demo.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    console.print(f"main job done; results in {out.resolve()}")


def _overrides(pairs: list[str]) -> dict:
    """``key=value`` pairs (values parsed as YAML: numbers, lists, booleans)."""
    import yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            _fail(f"--set takes key=value, got {pair!r}")
        out[key.strip()] = yaml.safe_load(value)
    return out


@app.command()
def simulate(
    protocol: Annotated[str, typer.Argument(help="Protocol: experiment1, campaign, or a YAML path.")],
    set_: Annotated[
        list[str] | None, typer.Option("--set", help="Override a protocol parameter: key=value (repeatable).")
    ] = None,
    benches: Annotated[int, typer.Option(help="Twin benches stepped together (batch size).")] = 128,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Run a protocol on the twin in simulated time: the same sessions as on the rig, much faster."""
    import time

    from rich.progress import Progress

    from acquisition.plans.sim_runner import simulate_protocol

    start = time.perf_counter()
    sessions_dir = Settings.lab / "sessions"
    with Progress(console=console, disable=Settings.quiet, transient=True) as bar:
        tasks: dict[str, int] = {}

        def progress(label: str, fraction: float) -> None:
            if label not in tasks:
                tasks[label] = bar.add_task(label, total=1.0)
            bar.update(tasks[label], completed=fraction)

        try:
            reports = simulate_protocol(
                protocol, sessions_dir, seed=seed, benches=benches, overrides=_overrides(set_ or []),
                progress=progress,
            )  # fmt: skip
        except (ValueError, FileNotFoundError, RobotDescriptionError) as exc:
            _fail(str(exc))
    wall = time.perf_counter() - start
    written = sum(len(r.sessions) for r in reports)
    skipped = sum(len(r.skipped) for r in reports)
    simulated = sum(r.simulated_s for r in reports)
    messages = sum(r.messages for r in reports)
    console.print(
        f"{protocol}: {written} sessions written, {skipped} already complete; {simulated:,.0f} bench-seconds "
        f"simulated in {wall:.1f} s ({simulated / wall:,.0f}× real time), {messages:,} messages "
        f"→ {sessions_dir}"
    )


@app.command()
def record(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    ports: Annotated[
        Path | None, typer.Option(help="ports.json (or the rig's run directory) naming each device's port.")
    ] = None,
    rig: Annotated[
        bool, typer.Option("--rig", help="Start a rig (the twin behind emulators) to record.")
    ] = False,
    duration: Annotated[float, typer.Option(help="Seconds to record (0: until Ctrl-C).")] = 0.0,
    session: Annotated[str | None, typer.Option(help="Session id (default: time, robot).")] = None,
    protocol: Annotated[str, typer.Option(help="What this session is (stored in its metadata).")] = "manual",
    live: Annotated[
        bool, typer.Option("--live", help="Serve the streams to Foxglove over WebSocket while recording.")
    ] = False,
    live_host: Annotated[str, typer.Option(help="Address the live view binds to.")] = "127.0.0.1",
    live_port: Annotated[int, typer.Option(help="Port of the live view (0: any free one).")] = 8765,
) -> None:
    """Record every device of a robot to one MCAP session, with live counters; Ctrl-C stops cleanly."""
    import contextlib
    import signal
    import subprocess
    import sys
    import time

    from rich.live import Live

    from acquisition.recorder.recorder import Recorder
    from acquisition.sim.ptyhost import wait_for_ports

    desc = _robot(robot)
    session_id = session or time.strftime("%Y%m%d-%H%M%S") + f"-{desc.name}"
    rig_proc = None
    if rig:
        run_dir = Settings.lab / "rig" / session_id
        rig_proc = subprocess.Popen(
            [sys.executable, "-m", "acquisition.sim.rig", "--robot", desc.name, "--run-dir", str(run_dir)]
        )
        ports = run_dir
    if ports is None:
        _fail("say where the devices are: --ports <ports.json | rig run dir>, or --rig")
    try:
        if rig or ports.is_dir():
            port_map = wait_for_ports(ports, timeout_s=60)
        elif ports.is_file():
            port_map = json.loads(ports.read_text())
        else:
            _fail(f"no ports file or rig directory at {ports}")
        stop = {"now": False}

        def on_signal(signum, frame):
            stop["now"] = True

        signal.signal(signal.SIGTERM, on_signal)
        view = _live_view(desc, live_host, live_port) if live else contextlib.nullcontext()
        with view as live_server:
            rec = Recorder(desc, port_map, Settings.lab / "sessions" / session_id, session_id,
                           protocol=protocol, live=live_server)  # fmt: skip
            start = time.monotonic()
            with rec, Live(console=console, refresh_per_second=2, transient=False) as counters:
                try:
                    while not stop["now"] and (duration <= 0 or time.monotonic() - start < duration):
                        time.sleep(0.5)
                        if not Settings.quiet:
                            counters.update(_counter_table(rec.snapshot(), time.monotonic() - start))
                except KeyboardInterrupt:
                    pass
        if rec.live_errors:
            console.print(f"[yellow]the live view failed {rec.live_errors} time(s); the file is complete[/]")
        if rec.write_error:
            _fail(f"the session writer failed: {rec.write_error}")
        console.print(f"session {session_id}: {', '.join(p.name for p in rec.writer.parts)} in "
                      f"{rec.writer.directory}")  # fmt: skip
    finally:
        if rig_proc is not None:
            rig_proc.terminate()
            rig_proc.wait(timeout=10)


def _live_view(desc, host: str, port: int):
    """A started Foxglove live view of ``desc``'s topics; tells the user where to point Foxglove."""
    import ipaddress

    from acquisition.recorder.live import LiveServer
    from acquisition.schemas.topics import session_topics

    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        console.print(f"[yellow]warning: the live view on {host} is unauthenticated: anyone who can reach "
                      f"it sees the streams[/]")  # fmt: skip
    try:
        server = LiveServer(session_topics(desc), host=host, port=port).start()
    except Exception as exc:  # a port in use, an address not ours
        _fail(f"cannot start the live view on {host}:{port}: {exc}")
    console.print(f"live view: open {server.url} in Foxglove (Open connection → Foxglove WebSocket)")
    return server


def _counter_table(snapshot: dict, elapsed: float) -> Table:
    table = Table("topic", "received", "written", "dropped", "rate Hz", title=f"recording {elapsed:.0f} s")
    for topic, c in sorted(snapshot.items()):
        rate = c["received"] / elapsed if elapsed > 0 else 0.0
        table.add_row(topic, f"{c['received']:,}", f"{c['written']:,}", str(c["dropped"]), f"{rate:.0f}")
    return table


@sessions_app.command("list")
def sessions_list() -> None:
    """Sessions in the lab: robot, protocol, status, duration, streams, drops."""
    from acquisition.recorder.sessions import list_sessions

    table = Table("session", "robot", "protocol", "status", "duration s", "messages", "dropped", "torn parts")
    for info in list_sessions(Settings.lab / "sessions"):
        table.add_row(
            info.id, info.robot, info.protocol, info.status, f"{info.duration_s:.1f}",
            f"{sum(s.messages for s in info.streams.values()):,}", str(info.dropped), str(len(info.torn)),
        )  # fmt: skip
    console.print(table)


def _session_dir(session: str) -> Path:
    directory = Path(session) if Path(session).is_dir() else Settings.lab / "sessions" / session
    if not directory.is_dir():
        _fail(f"no session {session!r} in {Settings.lab / 'sessions'}")
    return directory


@sessions_app.command("info")
def sessions_info(session: Annotated[str, typer.Argument(help="Session id or directory.")]) -> None:
    """One session's streams: messages, time span, rate, drops."""
    from acquisition.recorder.sessions import session_info

    info = session_info(_session_dir(session))
    table = Table(
        "topic", "messages", "duration s", "rate Hz", "dropped",
        title=f"{info.id}: {info.robot}, {info.protocol}, {info.status}, {len(info.parts)} part(s)",
    )  # fmt: skip
    for s in info.streams.values():
        table.add_row(s.topic, f"{s.messages:,}", f"{s.duration_s:.2f}", f"{s.rate_hz:.1f}", str(s.dropped))
    console.print(table)
    for part in info.torn:
        console.print(f"[yellow]torn part[/yellow] {part.name}: run `vslab sessions recover {info.id}`")


@sessions_app.command("recover")
def sessions_recover(session: Annotated[str, typer.Argument(help="Session id or directory.")]) -> None:
    """Write a valid, indexed copy of every torn part (the originals are never changed)."""
    from acquisition.recorder.sessions import recover_session

    reports = recover_session(_session_dir(session))
    if not reports:
        console.print("nothing to recover: every part is whole")
    for r in reports:
        console.print(
            f"{r.source.name} → {r.output.name}: {r.messages:,} messages ({r.reason or 'complete'})"
        )


def _print_grid(grid, title: str) -> None:
    if Settings.quiet:
        return
    table = Table(title=title)
    table.add_column("pressure")
    for col in grid.columns:
        table.add_column(str(col), justify="right")
    for idx, row in grid.iterrows():
        table.add_row(str(idx), *(f"{v:.2f}" for v in row))
    console.print(table)


if __name__ == "__main__":  # pragma: no cover
    app(prog_name=os.path.basename(__file__))
