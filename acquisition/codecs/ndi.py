"""NDI Aurora serial API codec (commands, replies, TX and BX frames): pure functions, no I/O.

Wire facts (``shared/reference/devices.md``, "NDI Aurora serial API"): commands are ``CMD:params`` + 4
hex CRC-16/ARC + ``\\r`` (or ``CMD params\\r`` without CRC); replies are text + 4 hex CRC + ``\\r``; ``TX``
answers text transforms (mm, ×1e4 fixed point), ``BX`` a little-endian binary frame. Units here are the
wire's: millimetres for positions and RMS error (the drivers convert to metres).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from acquisition.errors import CodecError

BX_START = b"\xc4\xa5"
BX_VALID, BX_MISSING, BX_DISABLED = 1, 2, 4
_TX_TRANSFORM_LEN = 51


class NdiCrcError(CodecError):
    """A command or reply failed its CRC-16 check."""


class NdiFormatError(CodecError):
    """A command or reply does not follow the NDI framing."""


def crc16_arc(data: bytes) -> int:
    """CRC-16/ARC (reflected poly 0xA001, init 0, no final xor), the NDI command and reply CRC."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


# exactly four hex digits: int(x, 16) alone also takes " ABC", "+ABC" and "A_BC", so a space or sign garbled
# over a CRC's leading 0 (or an underscore between digits) went through as that CRC
_CRC_DIGITS = re.compile(rb"[0-9A-Fa-f]{4}")


def _hex_crc(data: bytes) -> bytes:
    """The 4 uppercase hex digits of the CRC of ``data``."""
    return b"%04X" % crc16_arc(data)


# ---------------------------------------------------------------------------------------------- commands
def format_command(name: str, params: str = "") -> bytes:
    """``CMD:params`` + CRC + ``\\r`` (the form ndicapi sends)."""
    body = f"{name}:{params}".encode("ascii")
    return body + _hex_crc(body) + b"\r"


def parse_command(line: bytes) -> tuple[str, str]:
    """``CMD:params`` + CRC (checked) or ``CMD params`` (no CRC), with or without ``\\r`` → (name, params).

    A colon form with fewer than 4 characters after the colon (``INIT:``) is accepted without a CRC.
    """
    line = line.rstrip(b"\r")
    if b":" in line:
        name, _, rest = line.partition(b":")
        if not re.fullmatch(rb"[A-Za-z0-9]+", name):
            raise NdiFormatError(f"bad command name in {line!r}")
        if len(rest) < 4:
            return name.decode("ascii").upper(), rest.decode("ascii", "replace")
        params, crc_text = rest[:-4], rest[-4:]
        if not _CRC_DIGITS.fullmatch(crc_text):
            raise NdiFormatError(f"bad CRC digits in {line!r}")
        got = int(crc_text, 16)
        want = crc16_arc(name + b":" + params)
        if got != want:
            raise NdiCrcError(f"command {line!r}: CRC {got:04X} != {want:04X}")
        return name.decode("ascii").upper(), params.decode("ascii", "replace")
    name, _, params = line.partition(b" ")
    if not re.fullmatch(rb"[A-Za-z0-9]+", name):
        raise NdiFormatError(f"bad command name in {line!r}")
    return name.decode("ascii").upper(), params.decode("ascii", "replace")


# ----------------------------------------------------------------------------------------------- replies
def format_reply(text: str) -> bytes:
    """Reply text + 4 uppercase hex CRC of the text + ``\\r``."""
    body = text.encode("ascii")
    return body + _hex_crc(body) + b"\r"


def parse_reply(data: bytes) -> str:
    """Check a text reply's CRC and return the text without CRC and ``\\r``."""
    data = data.rstrip(b"\r")
    if len(data) < 4:
        raise NdiFormatError(f"reply too short: {data!r}")
    body, crc_text = data[:-4], data[-4:]
    if not _CRC_DIGITS.fullmatch(crc_text):
        raise NdiFormatError(f"bad CRC digits in reply {data!r}")
    got = int(crc_text, 16)
    want = crc16_arc(body)
    if got != want:
        raise NdiCrcError(f"reply {data[:40]!r}: CRC {got:04X} != {want:04X}")
    try:
        return body.decode("ascii")
    except UnicodeDecodeError as exc:  # a matching CRC over bytes that are not text
        raise NdiFormatError(f"reply {data[:40]!r} is not ASCII text") from exc


def error_reply(code: int) -> bytes:
    """``ERRORxx`` reply (xx = NDI error code, 2 uppercase hex digits)."""
    return format_reply(f"ERROR{code:02X}")


# ------------------------------------------------------------------------------------------ frame record
@dataclass
class HandleFrame:
    """One port handle in a TX/BX reply; position in mm, quaternion (q0, qx, qy, qz), wire units."""

    handle: int
    quaternion: tuple[float, float, float, float]
    position_mm: tuple[float, float, float]
    rms_error: float
    port_status: int
    frame: int
    missing: bool
    disabled: bool = False


_NAN4 = (float("nan"),) * 4
_NAN3 = (float("nan"),) * 3


# -------------------------------------------------------------------------------------------------- TX
def _tx_transform(h: HandleFrame) -> str:
    """The 51-character TX transform field."""
    q = "".join(f"{round(v * 1e4):+06d}" for v in h.quaternion)
    t = "".join(f"{round(v * 100):+07d}" for v in h.position_mm)
    return q + t + f"{round(h.rms_error * 1e4):+06d}"


def format_tx(handles: list[HandleFrame], system_status: int = 0) -> str:
    """TX:0801 reply text (before the CRC) for ``handles``."""
    parts = [f"{len(handles):02X}"]
    for h in handles:
        if h.disabled:
            body = "DISABLED"
        elif h.missing:
            body = "MISSING"
        else:
            body = _tx_transform(h)
        parts.append(f"{h.handle:02X}{body}{h.port_status & 0xFFFFFFFF:08X}{h.frame & 0xFFFFFFFF:08X}\n")
    parts.append(f"{system_status & 0xFFFF:04X}")
    return "".join(parts)


def _signed(text: str, scale: float) -> float:
    """A ``%+0Nd`` field divided by ``scale``."""
    if text[:1] not in "+-" or not (text[1:].isascii() and text[1:].isdigit()):  # not '²': int() refuses it
        raise NdiFormatError(f"bad signed field {text!r}")
    return int(text) / scale


def parse_tx(text: str) -> list[HandleFrame]:
    """Parse TX:0801 reply text (no CRC) → handle frames; MISSING/DISABLED carry NaN poses."""
    try:
        count = int(text[:2], 16)
    except ValueError as exc:
        raise NdiFormatError(f"bad TX handle count in {text[:20]!r}") from exc
    pos = 2
    out: list[HandleFrame] = []
    for _ in range(count):
        try:
            handle = int(text[pos : pos + 2], 16)
        except ValueError as exc:
            raise NdiFormatError(f"bad TX handle {text[pos : pos + 2]!r} at {pos}") from exc
        pos += 2
        missing = disabled = False
        quat, trans, rms = _NAN4, _NAN3, float("nan")
        if text.startswith("MISSING", pos):
            missing, pos = True, pos + 7
        elif text.startswith("DISABLED", pos):
            disabled, pos = True, pos + 8
        else:
            f = text[pos : pos + _TX_TRANSFORM_LEN]
            if len(f) != _TX_TRANSFORM_LEN:
                raise NdiFormatError(f"TX transform truncated: {f!r}")
            quat = tuple(_signed(f[i * 6 : i * 6 + 6], 1e4) for i in range(4))
            trans = tuple(_signed(f[24 + i * 7 : 31 + i * 7], 100.0) for i in range(3))
            rms = _signed(f[45:51], 1e4)
            pos += _TX_TRANSFORM_LEN
        status_frame = text[pos : pos + 16]
        if disabled and not re.fullmatch(r"[0-9A-Fa-f]{16}", status_frame):
            port_status, frame = 0, 0  # a disabled handle may carry no status/frame
        else:
            try:
                port_status, frame = int(status_frame[:8], 16), int(status_frame[8:], 16)
            except ValueError as exc:
                raise NdiFormatError(f"bad TX status/frame {status_frame!r}") from exc
            pos += 16
        if text[pos : pos + 1] == "\n":
            pos += 1
        out.append(HandleFrame(handle, quat, trans, rms, port_status, frame, missing, disabled))  # type: ignore[arg-type]
    return out


def parse_tx_system_status(text: str) -> int:
    """The 4-hex system status at the end of a TX reply text."""
    try:
        return int(text[-4:], 16)
    except ValueError as exc:
        raise NdiFormatError(f"bad TX system status {text[-4:]!r}") from exc


# -------------------------------------------------------------------------------------------------- BX
def format_bx(handles: list[HandleFrame], system_status: int = 0) -> bytes:
    """BX:0801 binary reply (header, body, body CRC), little-endian."""
    body = bytearray(struct.pack("<B", len(handles)))
    for h in handles:
        if h.disabled:
            body += struct.pack("<BB", h.handle, BX_DISABLED)
            continue
        if h.missing:
            body += struct.pack("<BB", h.handle, BX_MISSING)
        else:
            body += struct.pack("<BB", h.handle, BX_VALID)
            body += struct.pack("<8f", *h.quaternion, *h.position_mm, h.rms_error)
        body += struct.pack("<II", h.port_status & 0xFFFFFFFF, h.frame & 0xFFFFFFFF)
    body += struct.pack("<H", system_status & 0xFFFF)
    head = BX_START + struct.pack("<H", len(body))
    head += struct.pack("<H", crc16_arc(head))
    return bytes(head) + bytes(body) + struct.pack("<H", crc16_arc(bytes(body)))


def bx_total_length(header: bytes) -> int:
    """Whole BX reply length from its 6-byte header (checks start bytes and header CRC)."""
    if header[:2] != BX_START or len(header) < 6:
        raise NdiFormatError(f"BX reply does not start with C4 A5 and a 4-byte header: {header[:6].hex()}")
    (length, crc) = struct.unpack_from("<HH", header, 2)
    if crc16_arc(header[:4]) != crc:
        raise NdiCrcError(f"BX header CRC {crc:04X} != {crc16_arc(header[:4]):04X}")
    return 6 + length + 2


def parse_bx(data: bytes) -> list[HandleFrame]:
    """Parse a BX:0801 reply (header and body CRC checked) → handle frames."""
    total = bx_total_length(data[:6])
    if len(data) < total:
        raise NdiFormatError(f"BX reply truncated: {len(data)} of {total} bytes")
    body = data[6 : total - 2]
    (crc,) = struct.unpack_from("<H", data, total - 2)
    if crc16_arc(body) != crc:
        raise NdiCrcError(f"BX body CRC {crc:04X} != {crc16_arc(body):04X}")
    try:
        return _parse_bx_body(body)
    except struct.error as exc:
        raise NdiFormatError(f"BX body malformed: {exc}") from exc


def _parse_bx_body(body: bytes) -> list[HandleFrame]:
    """The handles of a CRC-checked BX body."""
    (count,) = struct.unpack_from("<B", body, 0)
    pos = 1
    out: list[HandleFrame] = []
    for _ in range(count):
        handle, status = struct.unpack_from("<BB", body, pos)
        pos += 2
        if status == BX_DISABLED:
            out.append(HandleFrame(handle, _NAN4, _NAN3, float("nan"), 0, 0, False, True))
            continue
        quat, trans, rms = _NAN4, _NAN3, float("nan")
        if status != BX_MISSING:
            vals = struct.unpack_from("<8f", body, pos)
            quat, trans, rms = tuple(vals[:4]), tuple(vals[4:7]), vals[7]
            pos += 32
        port_status, frame = struct.unpack_from("<II", body, pos)
        pos += 8
        out.append(HandleFrame(handle, quat, trans, rms, port_status, frame, status == BX_MISSING))  # type: ignore[arg-type]
    return out
