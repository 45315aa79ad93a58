"""Whether a session could run as the robot description says, device by device: one finding per check, each
problem with the command or line that fixes it. Only reads and pings go to the devices.

Checks: the user may open the port (dialout); the device answers at the description's baud (else the baud it
answers at); the servos' IDs and Return Delay Time; the USB adapter's latency timer (sysfs); and the bus
budget: the configured rate against the ceiling the found baud, return delay and latency timer allow
(``acquisition.devices.bus_budget``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from acquisition.bringup.probes import (
    dynamixel_bauds,
    find_servos,
    probe_aurora,
    probe_board,
    probe_slcan,
    servo_settings,
)
from acquisition.bringup.scan import DRIVER_OF, BringupError
from acquisition.devices.bus_budget import (
    DYNAMIXEL_BAUDS,
    DYNAMIXEL_FACTORY_RETURN_DELAY,
    DYNAMIXEL_RETURN_DELAY_UNIT_S,
    SerialLink,
    ceiling_line,
    servo_ceiling_hz,
)
from models.robot import DeviceSpec, RobotDescription

SYSFS = Path("/sys")
SYNC_READ_BYTES = 16  # the recorder's Sync Read: Realtime Tick … Present Position, addresses 120–135
UDEV_RULE = 'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1"'
UDEV_FILE = "/etc/udev/rules.d/99-vslab-ftdi.rules"


@dataclass(frozen=True)
class Finding:
    """One check of one device: ``ok`` or a problem, what was found, and the fix (empty when ok)."""

    device: str
    ok: bool
    what: str
    fix: str = ""


def return_delay_units(seconds: float) -> int:
    """The Return Delay Time (2 µs units) the description's ``return_delay_s`` means."""
    return round(seconds / DYNAMIXEL_RETURN_DELAY_UNIT_S)


def latency_timer_file(port: str, sysfs_root: Path) -> Path | None:
    """The port's adapter's ``latency_timer`` under ``sysfs_root`` (by the port's name, or the device node's
    it links to), None for a port without one (not an FTDI adapter)."""
    names = dict.fromkeys([Path(port).name, Path(os.path.realpath(port)).name])
    for name in names:
        path = sysfs_root / "bus" / "usb-serial" / "devices" / name / "latency_timer"
        if path.is_file():
            return path
    return None


def sysfs_for(port: str) -> Path:
    """Where a port's sysfs is: a rig's run directory carries its emulated adapters' (``sysfs/``), hardware
    the computer's (/sys)."""
    rig = Path(port).parent / "sysfs"
    return rig if rig.is_dir() else SYSFS


def check_permission(name: str, port: str) -> Finding:
    """Whether this user may open ``port`` for reading and writing (a lab computer's user joins dialout)."""
    if not os.path.exists(port):
        return Finding(name, False, f"{port}: no such port", "plug the device in; `vslab devices scan`")
    if os.access(port, os.R_OK | os.W_OK):
        return Finding(name, True, f"{port}: this user may open it")
    return Finding(name, False, f"{port}: this user may not open it",
                   "sudo usermod -aG dialout $USER, then log out and in again")  # fmt: skip


def check_latency_timer(name: str, spec: DeviceSpec, port: str, sysfs_root: Path) -> tuple[Finding, float]:
    """The adapter's latency timer against the description's (a finding, and the timer in seconds)."""
    path = latency_timer_file(port, sysfs_root)
    wanted = spec.host_link.latency_timer_s
    if path is None:
        return Finding(name, True, "no USB latency timer on this port (not an FTDI adapter)"), 0.0
    try:
        ms = int(path.read_text().strip())
    except (OSError, ValueError) as exc:
        return Finding(name, False, f"{path}: unreadable ({exc})", "check the adapter's driver"), wanted
    if ms * 1e-3 <= wanted + 1e-9:
        return Finding(name, True, f"latency timer {ms} ms"), ms * 1e-3
    fix = (f"echo {round(wanted * 1e3)} | sudo tee {path} (now); for good, the udev rule {UDEV_RULE} in "
           f"{UDEV_FILE}")  # fmt: skip
    return Finding(
        name, False, f"latency timer {ms} ms, the description says {wanted * 1e3:g} ms", fix
    ), ms * 1e-3


def check_servos(name: str, spec: DeviceSpec, port: str, latency_s: float, configure: str) -> list[Finding]:
    """A Dynamixel bus: reachable at the description's baud, IDs, Return Delay Time, the bus budget."""
    wanted_ids = sorted(spec.ids.values())
    bus = find_servos(port, dynamixel_bauds(spec.baud), max(wanted_ids), every_baud=True)
    if not bus.bauds:
        foreign_device(name, spec, port)
        bauds = ", ".join(f"{b:,}" for b in DYNAMIXEL_BAUDS.values())
        return [Finding(name, False, f"no servo answers at any baud ({bauds})",
                        "check the servos' power and cable; `vslab devices scan`")]  # fmt: skip
    out = []
    others = [b for b in bus.bauds if b != spec.baud]
    if others:
        out.append(Finding(name, False, f"servos answer at {', '.join(f'{b:,}' for b in others)} baud, the "
                                        f"description says {spec.baud:,}", configure))  # fmt: skip
    else:
        out.append(Finding(name, True, f"servos answer at {spec.baud:,} baud"))
    found_ids = sorted(s.dxl_id for s in bus.servos)
    if bus.garbled:
        out.append(Finding(name, False, "servos answer over each other: more than one has the same ID (new "
                                        "servos all have ID 1)", configure))  # fmt: skip
    elif found_ids != wanted_ids:
        out.append(
            Finding(name, False, f"servo IDs {found_ids}, the description says {wanted_ids}", configure)
        )
    else:
        out.append(Finding(name, True, f"servo IDs {found_ids}"))
    settings = servo_settings(port, list(bus.servos))
    delays = sorted({v["return_delay"] for v in settings.values() if v["return_delay"] is not None})
    want = return_delay_units(spec.return_delay_s)
    if bus.garbled:  # a read collides as the ping did: what new servos hold
        delays = [DYNAMIXEL_FACTORY_RETURN_DELAY]
        out.append(Finding(name, False, f"Return Delay Time unreadable while servos share an ID (new servos: "
                                        f"{delays[0]}), the description says {want}", configure))  # fmt: skip
    elif delays != [want]:
        out.append(Finding(name, False, f"Return Delay Time {delays} (2 µs units), the description says "
                                        f"{want}", configure))  # fmt: skip
    else:
        out.append(Finding(name, True, f"Return Delay Time {want}"))
    baud = spec.baud if spec.baud in bus.bauds else bus.bauds[0]
    out.append(check_budget(name, spec, baud, max(delays or [0]), latency_s))
    return out


def check_budget(name: str, spec: DeviceSpec, baud: int, return_delay: int, latency_s: float) -> Finding:
    """The configured rate against the ceiling of the link as found."""
    ceiling = servo_ceiling_hz(SerialLink(baud, latency_s), len(spec.ids), SYNC_READ_BYTES, return_delay)
    rate = spec.rate_hz or 0.0
    where = f"(at {baud:,} baud, Return Delay Time {return_delay}, latency timer {latency_s * 1e3:g} ms)"
    if rate > ceiling:
        return Finding(name, False, f"bus budget {where}", ceiling_line(name, rate, ceiling))
    return Finding(name, True, f"bus budget: {rate:g} Hz of at most {ceiling:.0f} Hz {where}")


def foreign_device(name: str, spec: DeviceSpec, port: str) -> None:
    """Raise BringupError when another kind of device than ``spec``'s answers on ``port`` (a ports file
    naming the wrong port): nothing this device's checks could say is about it."""
    probes = [p for d, p in (("ndi_aurora", probe_aurora), ("popup_can", probe_slcan)) if d != spec.driver]
    if spec.driver == "dynamixel" or not spec.driver.startswith("vslab_"):
        probes.append(probe_board)
    for probe in probes:
        if (answer := probe(port)) is not None:
            raise BringupError(wrong_port(name, port, answer.ident, spec.driver))


def wrong_port(name: str, port: str, ident: str, driver: str) -> str:
    """The line for a port where another device answers."""
    return (f"{name}: {port}: {ident} answers there, not a {driver}: the ports file names another device's "
            "port (`vslab devices scan --out ports.json`)")  # fmt: skip


def check_line_device(name: str, spec: DeviceSpec, port: str) -> Finding:
    """An Aurora, a board or an slcan adapter answers as the device the description names."""
    probe = {"ndi_aurora": probe_aurora, "popup_can": probe_slcan}.get(spec.driver)
    answer = probe(port) if probe else probe_board(port, spec.baud)
    if answer is None:
        foreign_device(name, spec, port)
        return Finding(
            name, False, f"{port}: no {spec.driver} answers", "`vslab devices scan` finds where it is"
        )
    kind = answer.ident.split(" ")[0] if answer.kind == "board" else answer.kind
    if DRIVER_OF.get(kind) != spec.driver:
        raise BringupError(wrong_port(name, port, answer.ident, spec.driver))
    return Finding(name, True, f"{answer.ident} answers at {answer.baud:,} baud")


def diagnose(desc: RobotDescription, port_map: dict[str, str], sysfs_root: Path | None, configure: str
             ) -> list[Finding]:  # fmt: skip
    """Every check of every device ``port_map`` names (``configure``: the command that fixes the servos)."""
    findings = []
    for name, spec in desc.devices.items():
        if spec.bus is not None:
            continue  # reached through another device's port
        port = port_map.get(name)
        if port is None:
            findings.append(Finding(name, False, "no port for it", "`vslab devices scan --out ports.json`"))
            continue
        permission = check_permission(name, port)
        findings.append(permission)
        if not permission.ok:
            continue
        latency, latency_s = check_latency_timer(name, spec, port, sysfs_root or sysfs_for(port))
        findings.append(latency)
        if spec.driver == "dynamixel":
            findings += check_servos(name, spec, port, latency_s, configure)
        else:
            findings.append(check_line_device(name, spec, port))
    return findings
