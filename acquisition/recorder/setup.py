"""A recording set up from a port map: the ports checked before anything opens them, the session's id and
the recorder started and stopped, and what went wrong said once it stopped (the recorder itself refuses a
session that exists and a port map without the robot's devices).

What `vslab record`, `vslab run` and the main job share. Every problem a user can cause is a
:class:`SetupError` (or the recorder's own :class:`RecorderError`), one line naming what and where; nothing
here prints.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import stat
from collections.abc import Iterator
from pathlib import Path

from acquisition.errors import AcquisitionError
from acquisition.recorder.recorder import Recorder, RecorderError
from models.robot import RobotDescription

SESSION_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")


class SetupError(AcquisitionError, ValueError):
    """A recording that cannot be set up as asked (a bad session id, a port that is not a serial port, a
    sessions folder that cannot be written); nothing was recorded."""


def session_id(given: str | None, default: str) -> str:
    """``given`` (or ``default``) once it is a folder name under sessions/, checked before anything starts."""
    sid = default if given is None else given
    if not SESSION_ID.fullmatch(sid):
        raise SetupError(f"--session {sid!r}: a session id is a folder name: letters, digits, '.', '_' and "
                         "'-' (at most 128, not starting with '.' or '-')")  # fmt: skip
    return sid


def configured_ports(desc: RobotDescription) -> dict[str, str]:
    """The ports ``desc`` names for its devices (``devices.<name>.port``), checked; one line if none."""
    configured = {n: d.port for n, d in desc.devices.items() if d.port != "auto"}
    if not configured:
        raise SetupError(f"say where the devices are: --ports <ports.json | rig run dir>, --rig, or a port "
                         f"for each device in {desc.name}'s description (devices.<name>.port)")  # fmt: skip
    return checked_ports(desc, configured, f"{desc.name}'s description (devices.<name>.port)")


def ports_file(path: Path) -> dict[str, str]:
    """A ports file: a JSON object of device name → port path (or a rig's ``{"ports": {...}}``)."""
    try:
        port_map = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError) as exc:  # not JSON, not UTF-8, unreadable
        raise SetupError(
            f"--ports {path}: not a ports file ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    port_map = port_map.get("ports", port_map) if isinstance(port_map, dict) else None
    if not isinstance(port_map, dict) or not all(isinstance(v, str) and v for v in port_map.values()):
        raise SetupError(f"--ports {path}: expected a JSON object of device name → port path, like "
                         '{"servo_bus": "/dev/ttyUSB0"}')  # fmt: skip
    return port_map


def checked_ports(desc: RobotDescription, port_map: dict[str, str], source: str) -> dict[str, str]:
    """``port_map`` once every entry names a device of ``desc`` and a serial port this user may open (it is
    not opened here: opening an Arduino's port resets it); one error line naming the device otherwise."""
    if foreign := sorted(set(port_map) - set(desc.devices)):
        raise SetupError(f"{source}: {', '.join(foreign)}: {desc.name} has no such device (its devices: "
                         f"{', '.join(desc.devices)}; the ports of another robot?)")  # fmt: skip
    for name, port in port_map.items():
        if problem := not_a_serial_port(port):
            raise SetupError(f"{source}: {name}: {port}: {problem}")
    return port_map


def not_a_serial_port(port: str) -> str | None:
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


@contextlib.contextmanager
def recording(rec: Recorder) -> Iterator[Recorder]:
    """``rec`` started for the block and stopped after it; a sessions folder that cannot be written is a
    :class:`SetupError` (a recorder that cannot start raises its own error)."""
    try:
        rec.start()
    except OSError as exc:  # the sessions folder cannot be written
        raise SetupError(str(exc)) from exc
    try:
        yield rec
    finally:
        rec.stop()


def recording_failure(rec: Recorder) -> str | None:
    """Why a stopped recording failed (its writer failed, or no device gave a sample), or None."""
    if rec.write_error:
        return f"the session writer failed: {rec.write_error}"
    if rec.silent and len(rec.silent) == len(rec.devices):
        return "no device gave a sample: check the ports (`--ports`, or devices.<name>.port)"
    return None


__all__ = ["RecorderError", "SetupError", "checked_ports", "configured_ports", "ports_file", "recording",
           "recording_failure", "session_id"]  # fmt: skip
