"""slcan, the Lawicel serial-line CAN protocol that USB-CAN adapters (CANable, USBtin, CANUSB) speak, as
python-can's ``slcan`` interface uses it (``../shared/reference/can.md`` §1).

Lines end in CR. The host sends commands (``S8`` set 1 Mbit/s, ``O`` open, ``L`` open listen-only, ``C``
close, ``V``/``N`` version and serial number, ``F`` status flags) and frames: ``tIIILDD…`` (standard),
``TIIIIIIIILDD…`` (extended), ``rIIIL`` / ``RIIIIIIIIL`` (remote requests): uppercase hex, the DLC one
decimal digit. The adapter answers CR for OK and BEL for an error; a transmitted frame is acknowledged
``z`` (standard) or ``Z`` (extended). Received frames come as the same frame lines. This module only
encodes and parses; the adapter's emulator and the twin's bus use it, the driver uses python-can's own
(read in bulk: ``acquisition.devices.slcan_bus``).
"""

from __future__ import annotations

import re

from acquisition.codecs.can import CanFrame
from acquisition.errors import CodecError

CR, BEL = b"\r", b"\x07"
# S0–S9: the bit rates the Lawicel ``Sn`` command selects (bit/s)
BITRATES = {0: 10_000, 1: 20_000, 2: 50_000, 3: 100_000, 4: 125_000, 5: 250_000, 6: 500_000,
            7: 800_000, 8: 1_000_000, 9: 83_333}  # fmt: skip
FRAME_STARTS = b"tTrR"


def encode_frame(frame: CanFrame) -> bytes:
    """The slcan line (CR included) carrying ``frame``."""
    kind = ("R" if frame.remote else "T") if frame.extended else ("r" if frame.remote else "t")
    ident = f"{frame.can_id:08X}" if frame.extended else f"{frame.can_id:03X}"
    return f"{kind}{ident}{frame.length}{frame.data.hex().upper()}".encode("ascii") + CR


def parse_frame(line: bytes) -> CanFrame:
    """The frame of one slcan frame line (without its CR); trailing characters after the data (a Lawicel
    millisecond stamp) are ignored, as python-can does."""
    text = line.decode("ascii", errors="replace")
    if not text or text[0] not in "tTrR":
        raise CodecError(f"slcan: not a frame line: {text[:20]!r}")
    extended, remote = text[0] in "TR", text[0] in "rR"
    width = 8 if extended else 3
    # the identifier's digits and the length's digit, exactly (int() alone takes " 23", "+23", "2_3")
    if not re.fullmatch(f"[0-9A-Fa-f]{{{width}}}[0-8]", text[1 : 2 + width]):
        raise CodecError(f"slcan: malformed frame line {text[:30]!r}")
    can_id, dlc = int(text[1 : 1 + width], 16), int(text[1 + width])
    if remote:
        return CanFrame(can_id, b"", extended, True, dlc)
    hex_data = text[2 + width : 2 + width + 2 * dlc]
    try:
        data = bytes.fromhex(hex_data)
    except ValueError as exc:
        raise CodecError(f"slcan: bad data in {text[:30]!r}") from exc
    if len(data) != dlc:
        raise CodecError(f"slcan: frame line {text[:30]!r} has {len(data)} of its {dlc} data bytes")
    return CanFrame(can_id, data, extended)


def split_lines(buffer: bytearray) -> list[bytes]:
    """Take every complete line (CR or BEL terminated) out of ``buffer``, without terminators; a partial
    line stays for the next call."""
    lines = []
    start = 0
    for k, byte in enumerate(buffer):
        if byte in (0x0D, 0x07):
            lines.append(bytes(buffer[start:k]))
            start = k + 1
    del buffer[:start]
    return lines
