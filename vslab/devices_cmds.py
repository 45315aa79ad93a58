"""`vslab devices scan | doctor | configure`: finding a lab's devices, checking them against the robot
description, and setting new servos as it says."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from acquisition.errors import AcquisitionError
from vslab.app import _error, _robot, app, console, options

devices_app = typer.Typer(
    help="The lab's devices: find them, check them, set new servos up.", no_args_is_help=True
)
app.add_typer(devices_app, name="devices")

RigDir = Annotated[Path | None, typer.Option(help="A running rig's run directory (default: the lab's rig).")]


def _rig_dir(given: Path | None) -> Path | None:
    """The rig whose ports are scanned too: ``--rig-dir``, else the lab's rig folder when a rig runs there."""
    if given is not None:
        if not (given / "ports.json").is_file():
            _error(
                f"--rig-dir {given}: no ports.json there (is a rig running? `vslab rig --run-dir {given}`)"
            )
        return given
    try:
        default = Path(str(options().lab.rigs))
    except Exception:  # a lab on object storage has no local rig
        return None
    return default if (default / "ports.json").is_file() else None


def _port_map(desc, ports: Path | None) -> dict[str, str]:
    """The ports to check: ``--ports`` (a ports file or a rig's run directory), else the lab's running rig."""
    from acquisition.recorder.setup import SetupError, checked_ports, ports_file

    where = ports or _rig_dir(None)
    if where is None:
        _error("say where the devices are: --ports FILE (`vslab devices scan --out ports.json` writes one)")
    if where.is_dir():
        where = where / "ports.json"
    try:  # each entry a device of desc and a serial port this user may open
        return checked_ports(desc, ports_file(where), f"--ports {where}")
    except SetupError as exc:
        _error(str(exc))


@devices_app.command()
def scan(
    out: Annotated[Path | None, typer.Option(help="Write the ports file the recorder takes here.")] = None,
    robot: Annotated[str, typer.Option(help="Robot description whose devices are looked for.")] = "vsl",
    rig_dir: RigDir = None,
) -> None:
    """List the serial ports (and a running rig's) and what answers on each; reads and pings only."""
    from acquisition.bringup.scan import rig_ports, scan, usb_ports, write_ports

    desc = _robot(robot)
    where = _rig_dir(rig_dir)
    try:
        ports = usb_ports() + (rig_ports(where) if where is not None else [])
        found = scan(desc, ports)
        written = write_ports(out, found) if out is not None else None
    except AcquisitionError as exc:
        _error(str(exc))
    table = Table("port", "USB / rig", "answers", "baud", "device", title=f"serial ports ({desc.name})")
    for f in found:
        what = f.answer.ident if f.answer else (f.error or "nothing vslab knows")
        baud = f"{f.answer.baud:,}" if f.answer else ""
        table.add_row(escape(f.port.path), f.port.usb or f.port.rig, escape(what), baud, f.device or "")
    console.print(table)
    if written is not None:
        console.print(f"ports file: {out} ({', '.join(written) or 'no device found'})")
    if missing := [
        n for n, d in desc.devices.items() if d.bus is None and n not in {f.device for f in found}
    ]:
        console.print(f"[yellow]not found: {', '.join(missing)}[/]")


@devices_app.command()
def doctor(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    ports: Annotated[Path | None, typer.Option(help="Ports file (or a rig's run directory).")] = None,
    sysfs_root: Annotated[Path | None, typer.Option(help="sysfs root (default /sys; a rig's own).")] = None,
) -> None:
    """Check each device against the description: one line per finding, each problem with its fix; exit 1
    when a session could not run as described."""
    from acquisition.bringup.doctor import diagnose

    desc = _robot(robot)
    port_map = _port_map(desc, ports)
    configure = f"vslab devices configure --robot {robot}" + (f" --ports {ports}" if ports else "")
    try:
        findings = diagnose(desc, port_map, sysfs_root, configure)
    except (AcquisitionError, OSError) as exc:
        _error(str(exc))
    for f in findings:
        mark = "[green]ok[/]     " if f.ok else "[red]problem[/]"
        fix = f"\n           fix: {escape(f.fix)}" if f.fix else ""
        console.print(f"{mark} {f.device}: {escape(f.what)}{fix}", soft_wrap=True, highlight=False)
    if problems := sum(not f.ok for f in findings):
        console.print(f"{problems} problem(s): a session would not run as {desc.name}'s description says")
        raise typer.Exit(code=1)
    console.print(f"all well: {desc.name}'s devices are as described")


@devices_app.command()
def configure(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    ports: Annotated[Path | None, typer.Option(help="Ports file (or a rig's run directory).")] = None,
    yes: Annotated[
        bool, typer.Option("--yes", help="Write without asking (the table is still shown).")
    ] = False,
) -> None:
    """Set each servo's ID, Baud Rate and Return Delay Time as the description says (EEPROM, torque off),
    shown first, then verified at the new baud. New servos (all ID 1) are set one at a time: connect each when
    asked (on a rig, its control socket connects them)."""
    from acquisition.bringup import servo_setup

    desc = _robot(robot)
    port_map = _port_map(desc, ports)
    bus = next((n for n, d in desc.devices.items() if d.driver == "dynamixel"), None)
    if bus is None:
        _error(f"{desc.name} has no Dynamixel servo bus to configure")
    if bus not in port_map:
        _error(f"no port for {bus} in the ports given (`vslab devices scan --out ports.json`)")
    spec, port = desc.devices[bus], port_map[bus]
    try:
        rows = servo_setup.assigned_rows(port, spec)
        if rows is not None:
            _show(rows)
            _confirm(yes)
            _write(port, rows)
            return
        connect = _connector(port)
        connect([], "Disconnect every servo from the bus")
        done: list[str] = []
        for joint in servo_setup.assign_order(spec):
            connect([*done, joint], f"Connect the servo of {joint} (only it, beside those set already)")
            row = servo_setup.new_servo_row(port, spec, joint, done)
            _show([row])
            _confirm(yes)
            _write(port, [row])
            done.append(joint)
    except (AcquisitionError, OSError) as exc:
        _error(str(exc))
    console.print(f"{bus}: every servo set as {desc.name}'s description says")


def _connector(port: str):
    """How the next servo gets connected: a rig's control socket connects it; an operator is asked to."""
    from twin.ptyhost import CONTROL_SOCKET, send_control

    run_dir = Path(port).parent
    if (run_dir / CONTROL_SOCKET).exists():
        return lambda joints, _text: send_control(run_dir, {"op": "servos", "connected": joints})
    return lambda _joints, text: typer.prompt(f"{text}, then press Enter", default="", show_default=False)


def _show(rows) -> None:
    table = Table("joint", "found at", "ID", "Baud Rate", "Return Delay Time", title="servos: now → wanted")
    for r in rows:
        cells = [f"{r.now.get(k)} → {v}" if r.now.get(k) != v else f"{v}" for k, v in r.want.items()]
        table.add_row(r.joint, f"ID {r.servo.dxl_id} at {r.servo.baud:,}", *cells)
    console.print(table)


def _confirm(yes: bool) -> None:
    if not yes and not typer.confirm("Write these to the servos' EEPROM (torque off first)?", default=False):
        console.print("nothing written")
        raise typer.Exit(code=1)


def _write(port: str, rows) -> None:
    from acquisition.bringup.servo_setup import write_row

    for row in rows:
        if not row.changes:
            console.print(f"{row.joint}: already as described")
            continue
        if refused := write_row(port, row):
            _error(refused)
        console.print(f"{row.joint}: written and verified ({row.changes})")
