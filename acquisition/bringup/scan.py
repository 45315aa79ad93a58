"""Which serial ports a computer has and which of a robot's devices answers on each: the ports file the
recorder takes (``vslab record --ports FILE``), stable paths preferred (``/dev/serial/by-id``, a rig's links).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from serial.tools import list_ports

from acquisition.bringup.probes import Answer, identify
from acquisition.codecs import board_lines as bp
from acquisition.errors import AcquisitionError
from models.robot import RobotDescription

log = logging.getLogger(__name__)

BY_ID = Path("/dev/serial/by-id")
RIG_PORTS_FILE = "ports.json"  # what a rig publishes in its run directory (twin.ptyhost.PORTS_FILE)
# what answered → the driver of the description's device it is
DRIVER_OF = {"dynamixel": "dynamixel", "aurora": "ndi_aurora", "slcan": "popup_can",
             bp.BOARD_PRESSURE: "vslab_pressure_board", bp.BOARD_STEPPER: "vslab_stepper_board"}  # fmt: skip


class BringupError(AcquisitionError, ValueError):
    """A port, ports file or description that bringing the devices up cannot use: one line, naming it."""


@dataclass(frozen=True)
class Port:
    """One serial port: its path (the stable one where there is one), the device node, what the USB says."""

    path: str
    device: str
    usb: str = ""  # "VID:PID serial …" of a USB adapter
    rig: str = ""  # the rig device whose emulator serves this pseudo-terminal


@dataclass(frozen=True)
class Found:
    """A port and what answered on it (None: nothing that vslab knows), and the description's device it is."""

    port: Port
    answer: Answer | None
    device: str | None = None
    error: str = ""


def by_id_paths(root: Path = BY_ID) -> dict[str, str]:
    """Device node → its ``/dev/serial/by-id`` link (stable across replugging, unlike ``/dev/ttyUSB0``)."""
    if not root.is_dir():
        return {}
    return {os.path.realpath(link): str(link) for link in sorted(root.iterdir())}


def usb_ports() -> list[Port]:
    """The computer's serial ports as pyserial lists them, each with its by-id path where it has one."""
    stable = by_id_paths()
    ports = []
    for info in sorted(list_ports.comports(), key=lambda p: p.device):
        usb = (
            f"{info.vid:04X}:{info.pid:04X} serial {info.serial_number or '-'}"
            if info.vid is not None
            else ""
        )
        real = os.path.realpath(info.device)
        ports.append(Port(stable.get(real, info.device), info.device, usb))
    return ports


def rig_ports(rig_dir: Path) -> list[Port]:
    """The pseudo-terminals a running rig serves (its ``ports.json``), none when no rig runs there."""
    path = rig_dir / RIG_PORTS_FILE
    try:
        ports = json.loads(path.read_text())["ports"]
    except FileNotFoundError:
        return []
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BringupError(f"{path}: not a rig's ports file ({exc})") from None
    return [Port(link, os.path.realpath(link), rig=name) for name, link in ports.items()]


def device_for(desc: RobotDescription, answer: Answer | None, taken: set[str]) -> str | None:
    """The device of ``desc`` that ``answer`` is (the first of its driver not yet taken), None if none."""
    if answer is None:
        return None
    key = answer.ident.split(" ")[0] if answer.kind == "board" else answer.kind
    driver = DRIVER_OF.get(key)
    return next((n for n, d in desc.devices.items() if d.driver == driver and n not in taken), None)


def scan(desc: RobotDescription, ports: list[Port]) -> list[Found]:
    """Ask each port what answers there (reads and pings only), and which of ``desc``'s devices that is."""
    servo = next((d for d in desc.devices.values() if d.driver == "dynamixel"), None)
    max_id = max([1, *servo.ids.values()]) if servo else 8
    found: list[Found] = []
    taken: set[str] = set()
    for port in ports:
        try:
            answer = identify(port.path, max_id)
        except OSError as exc:
            found.append(Found(port, None, error=str(exc)))
            continue
        device = device_for(desc, answer, taken)
        taken |= {device} if device else set()
        found.append(Found(port, answer, device))
        log.info("%s: %s", port.path, answer)
    return found


def ports_map(found: list[Found]) -> dict[str, str]:
    """The ports file's contents: device name → its port's (stable) path."""
    return {f.device: f.port.path for f in found if f.device}


def write_ports(path: Path, found: list[Found]) -> dict[str, str]:
    """Write the ports file the recorder takes (``vslab record --ports``); what was written."""
    port_map = ports_map(found)
    try:
        path.write_text(json.dumps(port_map, indent=2) + "\n")
    except OSError as exc:
        raise BringupError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    return port_map
