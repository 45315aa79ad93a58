"""The load POPUP's CAN bus carries at the rates its robot description configures, before a session runs:
every frame kind the drives, the boards and the host send, its size (from the drive's EDS and the PDO
mapping the driver sets, from the boards' DBC), how often it goes, and the share of the bit rate it takes.

Two figures per frame kind (``bus_budget``): the **worst case**, every frame at its most stuff bits (the
bound a schedule must survive), and the **typical** one, the exact bits of frames of that identifier with
payloads drawn at random (a seeded draw: the same every run), which is what the twin's bus measures within
a few per cent. The host's side of the USB-CAN adapter is USB CDC: no baud limits it, but every frame it
receives is an slcan text line (``bus_budget.slcan_line_bytes``), counted too.

Not counted: SDO traffic (configuration, before a session), NMT, EMCY, the controlword RPDO (sent on state
changes only) and the main board's ``PressureCommand`` (sent when a plan commands pressures, at most at the
SYNC rate): each is rare beside the cyclic frames.
"""

from __future__ import annotations

import functools

import canopen
import numpy as np

from acquisition.codecs import popup_boards as pb
from acquisition.codecs.can import CanFrame
from acquisition.devices.bus_budget import can_frame_bits, can_frame_exact_bits, slcan_line_bytes
from acquisition.devices.can_drives import EDS, RPDO_MAP, TPDO_MAP
from acquisition.devices.kinds import device_of, kind_of

SYNC_ID, TPDO_BASE, RPDO_BASE, HEARTBEAT_BASE = 0x080, 0x180, 0x200, 0x700  # CiA 301 COB-IDs (+ node id)
HEARTBEAT_HZ = 10.0  # the driver sets each drive's producer heartbeat to 100 ms (CanDrives.heartbeat_ms)
TYPICAL_DRAWS = 64  # random payloads averaged per frame kind for the typical figure


@functools.cache
def pdo_bytes(objects: tuple[int, ...]) -> int:
    """Bytes of a PDO mapping ``objects`` (indices of the drive's EDS, sub-index 0)."""
    od = canopen.import_od(str(EDS), 1)
    return sum(len(od[index]) for index in objects) // 8


def typical_bits(can_id: int, n_bytes: int, seed: int = 0) -> float:
    """The mean exact bits of a frame ``can_id`` of ``n_bytes`` over ``TYPICAL_DRAWS`` random payloads."""
    rng = np.random.default_rng(seed)
    draws = [CanFrame(can_id, rng.bytes(n_bytes)) for _ in range(TYPICAL_DRAWS)]
    return float(np.mean([can_frame_exact_bits(f) for f in draws]))


def _row(what: str, can_ids: list[int], n_bytes: int, per_s: float, bitrate: int) -> dict:
    """One frame kind: ``per_s`` frames a second of each of ``can_ids``."""
    worst = can_frame_bits(n_bytes)
    typical = float(np.mean([typical_bits(i, n_bytes) for i in can_ids]))
    total = per_s * len(can_ids)
    return {"frame": what, "can_ids": can_ids, "bytes": n_bytes, "frames_per_s": total,
            "bits_worst": worst, "bits_typical": typical, "load_worst": total * worst / bitrate,
            "load_typical": total * typical / bitrate}  # fmt: skip


def drive_rows(node_ids: list[int], sync_hz: float, bitrate: int) -> list[dict]:
    """The CiA 402 drives' cyclic frames: SYNC, the TPDOs each SYNC triggers, the host's target RPDO per
    SYNC, and the heartbeats."""
    rows = [_row("SYNC", [SYNC_ID], 0, sync_hz, bitrate)]
    for n, objects in TPDO_MAP.items():
        ids = [TPDO_BASE + 0x100 * (n - 1) + i for i in node_ids]
        rows.append(_row(f"TPDO{n}", ids, pdo_bytes(objects), sync_hz, bitrate))
    ids = [RPDO_BASE + 0x100 + i for i in node_ids]  # RPDO2: the target position
    rows.append(_row("RPDO2", ids, pdo_bytes(RPDO_MAP[2]), sync_hz, bitrate))
    rows.append(_row("heartbeat", [HEARTBEAT_BASE + i for i in node_ids], 1, HEARTBEAT_HZ, bitrate))
    return rows


def board_rows(robot, bus: str, bitrate: int) -> list[dict]:
    """The frames of every board on ``bus``, each at its rate (the accelerometer at its output data rate)."""
    db = pb.database()
    accel_board = device_of(robot, "accelerometer")
    rows = []
    for name, dev in robot.devices.items():
        if dev.bus != bus:
            continue
        node = dev.ids["board"]
        if kind_of(robot, name).role == "pressure":
            streams = [(pb.MAIN_PRESSURE, dev.rate_hz), (pb.MAIN_STATUS, 1.0 / pb.STATUS_PERIOD_S)]
        else:
            streams = [(pb.link_message(node, pb.ORIENTATION), dev.rate_hz),
                       (pb.link_message(node, pb.FLEX), dev.rate_hz)]  # fmt: skip
            if name == accel_board:
                streams.append((pb.link_message(node, pb.ACCEL), robot.sensors.accelerometer.sample_rate_hz))
        for message, hz in streams:
            m = db.get_message_by_name(message)
            rows.append(_row(message, [m.frame_id], m.length, hz, bitrate))
    return rows


def popup_can_load(robot, bus: str = "can_bus") -> dict:
    """The load of ``robot``'s CAN bus ``bus`` at its configured rates: ``rows`` (one per frame kind) and
    ``total`` (frames per second, worst-case and typical load as fractions of the bit rate, and the
    characters per second the adapter sends the host)."""
    spec = robot.devices[bus]
    bitrate = int(spec.baud)
    rows = drive_rows(sorted(spec.ids.values()), float(spec.rate_hz), bitrate)
    rows += board_rows(robot, bus, bitrate)
    received = [r for r in rows if r["frame"] not in ("SYNC", "RPDO2")]  # what the host reads, not sends
    total = {
        "frames_per_s": sum(r["frames_per_s"] for r in rows),
        "load_worst": sum(r["load_worst"] for r in rows),
        "load_typical": sum(r["load_typical"] for r in rows),
        "slcan_bytes_per_s": sum(r["frames_per_s"] * slcan_line_bytes(r["bytes"]) for r in received),
    }
    return {"bitrate": bitrate, "sync_hz": float(spec.rate_hz), "rows": rows, "total": total}
