"""NDI Aurora emulator: the serial API that ndicapi / scikit-surgerynditracker speak, as a state machine.

One wired tool sits on port handle 0x0A. The frame source gives its pose at the rig's time; TX and BX replies
are built from it with :mod:`acquisition.codecs.ndi`. Error codes are NDI's (as ndicapi names them):
0x01 invalid command, 0x04 invalid CRC, 0x07 wrong number of parameters, 0x08 invalid port handle,
0x0C invalid in the current mode (e.g. TX before TSTART), 0x0E port handle not initialized.

Deviations from a real Aurora, on purpose: ``INIT`` is answered at any time and puts the tool back to its
power-up state (it stands in for the serial break + ``RESET`` a pty cannot carry, so a client that reopens
the port finds the tool to initialize again); ``GETINFO`` answers ``ERROR01`` (the probe then falls back to
``VER:0``, as with older Aurora firmware; UNVERIFIED which firmware supports GETINFO).

The serial line: 9,600 baud after power-up and ``RESET`` until ``COMM`` sets another rate, which
takes effect after its ``OKAY`` (sent at the old rate). The first open of the port stands for the break
ndicapi sends when its 9,600-baud probe goes unanswered (a pty cannot carry a break): the device is back at
9,600 baud, as the break's reset leaves it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from acquisition.codecs import ndi
from twin.emulators.base import Emulator

log = logging.getLogger(__name__)

TOOL_HANDLE = 0x0A
PORT_OCCUPIED, PORT_INITIALIZED, PORT_ENABLED, PORT_OUT_OF_VOLUME = 0x01, 0x10, 0x20, 0x40
POWER_UP_BAUD = 9_600
COMM_BAUDS = {"0": 9_600, "1": 14_400, "2": 19_200, "3": 38_400, "4": 57_600, "5": 115_200, "6": 921_600,
              "7": 1_228_739, "A": 230_400}  # fmt: skip  # COMM's first digit (reference/devices.md)
ERR_INVALID_COMMAND, ERR_BAD_CRC, ERR_PARAM_COUNT, ERR_BAD_HANDLE = 0x01, 0x04, 0x07, 0x08
ERR_BAD_MODE, ERR_NOT_INITIALIZED = 0x0C, 0x0E
_MAX_LINE = 1024

DEMO_CENTER_M = np.array([0.0, 0.0, -0.20])
DEMO_RADIUS_M = 0.05
DEMO_CIRCLE_HZ = 0.5
DEMO_FRAME_HZ = 40.0
DEMO_FRAME0 = 1000
DEMO_MISSING_PERIOD_S = 3.0
DEMO_MISSING_S = 0.5
DEMO_RMS_M = 0.48e-3


@dataclass
class TrackerSample:
    """The tool's state at one frame: position in m, quaternion (q0, qx, qy, qz), RMS error in m."""

    frame: int
    position_m: np.ndarray
    quaternion: np.ndarray
    rms_error: float
    missing: bool
    port_status: int


def _version_text(rev: str) -> str:
    """A ``VER 0`` reply in the shape a real Aurora gives (lines separated by ``\\n``)."""
    return "\n".join(
        [
            "Aurora Control Firmware",
            "NDI S/N: P6-00000",
            "Characterization Date: 01/01/20",
            f"Freeze Tag: AURORA Rev {rev}",
            "Freeze Date: 01/01/20",
            "(C) Northern Digital Inc.",
            "",
        ]
    )


class AuroraEmulator(Emulator):
    """Aurora with one tool on handle 0x0A; ``firmware_rev`` 007/008 makes sksurgerynditracker use TX,
    anything else BX."""

    name = "tracker"
    resets_on_open = True  # the open stands for ndicapi's break: 9,600 baud again (see the module's doc)

    def __init__(self, source: Callable[[float], TrackerSample], firmware_rev: str = "008") -> None:
        self.source = source
        self.firmware_rev = firmware_rev
        self._buffer = b""
        self.baud = POWER_UP_BAUD
        self._power_up()

    # state
    def _power_up(self) -> None:
        """Power-up state: tool occupied, not initialized, not enabled, not tracking (the baud: see
        ``_cmd_reset``)."""
        self.initialized = False
        self.enabled = False
        self.tracking = False

    def reset_link(self) -> None:
        """Drop half-received input after a replug."""
        self._buffer = b""

    def port_opened(self, now_s: float) -> None:
        """A client opened the port: it will probe at 9,600 baud and break the device back there."""
        self._buffer = b""
        self.baud = POWER_UP_BAUD

    def _port_status(self) -> int:
        """PHSR/TX port status bits for the tool (occupied, initialized, enabled)."""
        status = PORT_OCCUPIED
        if self.initialized:
            status |= PORT_INITIALIZED
        if self.enabled:
            status |= PORT_ENABLED
        return status

    # byte stream
    def feed(self, data: bytes, now_s: float) -> bytes:
        """Buffer bytes; answer each complete ``\\r``-terminated command."""
        self._buffer += data
        out = b""
        while b"\r" in self._buffer:
            line, _, self._buffer = self._buffer.partition(b"\r")
            line = line.lstrip(b"\x00\n ")  # a break or stray bytes leave NULs/newlines before a command
            if line:
                out += self._answer(line, now_s)
        if len(self._buffer) > _MAX_LINE:
            log.warning("tracker emulator: %d bytes without CR dropped", len(self._buffer))
            self._buffer = b""
        return out

    def _answer(self, line: bytes, now_s: float) -> bytes:
        """The reply to one command line (without ``\\r``)."""
        try:
            name, params = ndi.parse_command(line)
        except ndi.NdiCrcError:
            log.info("tracker emulator: bad CRC in %r", line)
            return ndi.error_reply(ERR_BAD_CRC)
        except ndi.NdiFormatError:
            log.info("tracker emulator: malformed command %r", line)
            return ndi.error_reply(ERR_INVALID_COMMAND)
        handler = getattr(self, f"_cmd_{name.lower()}", None)
        if handler is None:
            log.info("tracker emulator: unsupported command %r", line)
            return ndi.error_reply(ERR_INVALID_COMMAND)
        log.debug("tracker emulator: %s %r", name, params)
        return handler(params, now_s)

    # commands
    def _cmd_init(self, params: str, now_s: float) -> bytes:
        self._power_up()
        return ndi.format_reply("OKAY")

    def _cmd_reset(self, params: str, now_s: float) -> bytes:
        """A reset is a power-up: 9,600 baud after its reply (INIT keeps the rate: it initializes the
        system, not the serial line)."""
        self._power_up()
        reply = ndi.format_reply("RESET")
        self.baud = POWER_UP_BAUD
        return reply

    def _cmd_comm(self, params: str, now_s: float) -> bytes:
        baud = COMM_BAUDS.get(params[:1].upper())
        if baud is None:
            return ndi.error_reply(ERR_PARAM_COUNT)
        reply = ndi.format_reply("OKAY")  # at the old rate: the host's ``feed_at`` timed it so
        self.baud = baud
        return reply

    def _cmd_getinfo(self, params: str, now_s: float) -> bytes:
        return ndi.error_reply(ERR_INVALID_COMMAND)

    def _cmd_ver(self, params: str, now_s: float) -> bytes:
        return ndi.format_reply(_version_text(self.firmware_rev))

    def _cmd_echo(self, params: str, now_s: float) -> bytes:
        return ndi.format_reply(params)

    def _cmd_beep(self, params: str, now_s: float) -> bytes:
        return ndi.format_reply("1")  # 1 = the system beeped

    def _cmd_phsr(self, params: str, now_s: float) -> bytes:
        mode = params[:2] or "00"
        listed = {
            "00": True,
            "01": False,  # no handles waiting to be freed
            "02": not self.initialized,
            "03": self.initialized and not self.enabled,
            "04": self.enabled,
        }.get(mode)
        if listed is None:
            return ndi.error_reply(ERR_PARAM_COUNT)
        if not listed:
            return ndi.format_reply("00")
        return ndi.format_reply(f"01{TOOL_HANDLE:02X}{self._port_status():03X}")

    def _handle_of(self, params: str) -> int | None:
        """The port handle in the first two hex characters, or None."""
        try:
            return int(params[:2], 16)
        except ValueError:
            return None

    def _on_port(self, params: str, *, initialized: bool | None = None, enabled: bool | None = None) -> bytes:
        """PINIT, PENA and PDIS: refused unless ``params`` names our tool's port handle (and, to enable it,
        the tool is initialised); otherwise the port takes the given states and the answer is OKAY."""
        if self._handle_of(params) != TOOL_HANDLE:
            return ndi.error_reply(ERR_BAD_HANDLE)
        if enabled and not self.initialized:
            return ndi.error_reply(ERR_NOT_INITIALIZED)
        if initialized is not None:
            self.initialized = initialized
        if enabled is not None:
            self.enabled = enabled
        return ndi.format_reply("OKAY")

    def _cmd_pinit(self, params: str, now_s: float) -> bytes:
        return self._on_port(params, initialized=True)

    def _cmd_pena(self, params: str, now_s: float) -> bytes:
        return self._on_port(params, enabled=True)

    def _cmd_pdis(self, params: str, now_s: float) -> bytes:
        return self._on_port(params, enabled=False)

    def _cmd_tstart(self, params: str, now_s: float) -> bytes:
        self.tracking = True
        return ndi.format_reply("OKAY")

    def _cmd_tstop(self, params: str, now_s: float) -> bytes:
        self.tracking = False
        return ndi.format_reply("OKAY")

    def _frames(self, now_s: float) -> list[ndi.HandleFrame]:
        """The tool's handle frame at ``now_s`` (wire units: mm), DISABLED if not enabled."""
        if not self.initialized:
            return []
        sample = self.source(now_s)
        status = sample.port_status | self._port_status()
        return [
            ndi.HandleFrame(
                handle=TOOL_HANDLE,
                quaternion=tuple(float(v) for v in sample.quaternion),  # type: ignore[arg-type]
                position_mm=tuple(float(v) * 1e3 for v in sample.position_m),  # type: ignore[arg-type]
                rms_error=sample.rms_error * 1e3,
                port_status=status,
                frame=sample.frame,
                missing=sample.missing,
                disabled=not self.enabled,
            )
        ]

    def _cmd_tx(self, params: str, now_s: float) -> bytes:
        if not self.tracking:
            return ndi.error_reply(ERR_BAD_MODE)
        return ndi.format_reply(ndi.format_tx(self._frames(now_s), system_status=0))

    def _cmd_bx(self, params: str, now_s: float) -> bytes:
        if not self.tracking:
            return ndi.error_reply(ERR_BAD_MODE)
        return ndi.format_bx(self._frames(now_s), system_status=0)


# -------------------------------------------------------------------------------------------------- demo
def demo_sample(now_s: float) -> TrackerSample:
    """Coil on a 50 mm circle at 0.5 Hz about DEMO_CENTER_M, 40 Hz frames, MISSING 0.5 s every 3 s."""
    angle = 2.0 * math.pi * DEMO_CIRCLE_HZ * now_s
    position = DEMO_CENTER_M + DEMO_RADIUS_M * np.array([math.cos(angle), math.sin(angle), 0.0])
    quaternion = np.array([math.cos(angle / 2.0), 0.0, 0.0, math.sin(angle / 2.0)])  # yaw = angle
    missing = (now_s % DEMO_MISSING_PERIOD_S) >= DEMO_MISSING_PERIOD_S - DEMO_MISSING_S
    return TrackerSample(
        frame=int(now_s * DEMO_FRAME_HZ) + DEMO_FRAME0,
        position_m=position,
        quaternion=quaternion,
        rms_error=DEMO_RMS_M,
        missing=missing,
        port_status=PORT_OUT_OF_VOLUME if missing else 0,
    )


def demo_emulator() -> AuroraEmulator:
    """The demo Aurora (TX), for ``tracker=twin.emulators.aurora:demo_emulator``."""
    return AuroraEmulator(demo_sample)


def demo_emulator_bx() -> AuroraEmulator:
    """The demo with a firmware revision sksurgerynditracker does not list, so it uses BX instead of TX."""
    return AuroraEmulator(demo_sample, firmware_rev="009")
