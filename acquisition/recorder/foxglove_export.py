"""``vslab sessions export --foxglove``: one session as one MCAP file that opens ready-made in Foxglove.

The file holds every record of the session's parts, unchanged, plus the standard topics of
:mod:`acquisition.schemas.scene` made from its measured streams and the robot's URDF as an attachment.
Sessions recorded since vslab writes those topics already carry them (without the tracker's placement, which
a dataset fits later); the export makes them again, for older sessions and with ``--registration``. The
session itself is not touched (its parts are its record; their hashes version the datasets built on them).
"""

from __future__ import annotations

import math
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from acquisition.errors import AcquisitionError
from acquisition.recorder.sessions import SessionError, session_info
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.mcap_reader import metadata_records
from acquisition.schemas.mcap_writer import merge_with
from acquisition.schemas.scene import RATE_HZ, STANDARD_TOPICS, URDF_ATTACHMENT, Batch, Scene, SceneStream
from acquisition.schemas.session_card import SESSION_METADATA
from acquisition.storage import as_path
from models.robot import RobotDescription

# /tf and /joint_states are resampled from the measured streams, the fastest of which (servo state) runs at
# ≈ 500 Hz: a faster rate repeats the same pose and only multiplies the file (1 kHz: 20× the default's bytes)
MAX_RATE_HZ = 1000.0


class ExportError(AcquisitionError, ValueError):
    """An export asked for with values it cannot be written with (a rate that is not a finite, positive
    number of hertz within ``MAX_RATE_HZ``)."""


def check_rate(rate_hz: float) -> None:
    """``ExportError`` unless ``rate_hz`` is finite, positive and at most ``MAX_RATE_HZ`` (inf would write no
    /tf at all, 0 or less never ends)."""
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= MAX_RATE_HZ):
        raise ExportError(f"--rate-hz {rate_hz}: give a rate in Hz above 0 and at most {MAX_RATE_HZ:g} (the "
                          "measured streams run at ≤ 500 Hz; a faster /tf only repeats poses)")  # fmt: skip


def session_robot(part: Path) -> RobotDescription:
    """The robot description a part recorded (its session metadata)."""
    with as_path(part).open("rb") as f:
        for name, metadata in metadata_records(f):
            if name == SESSION_METADATA and "robot_description" in metadata:
                return RobotDescription.model_validate_json(metadata["robot_description"])
    raise SessionError(Path(str(part)).parent, f"{Path(str(part)).name} has no robot description")


def export_foxglove(session: Path, out: Path, base_to_tracker: np.ndarray | None = None,
                    rate_hz: float = RATE_HZ) -> int:  # fmt: skip
    """Write ``session`` with its standard topics into ``out`` (written whole, then renamed in); returns the
    messages written. ``SessionError`` for a folder that is not a readable session or has a torn or damaged
    part, ``ExportError`` for a rate out of bounds."""
    info = session_info(session)
    if info.torn:
        raise SessionError(
            info.directory, f"torn part {info.torn[0].name}", "run `vslab sessions recover` first"
        )
    check_rate(rate_hz)
    if info.damaged:  # every chunk is checked first: an export never leaves a damaged chunk's messages out
        raise SessionError(info.directory, f"cannot be exported whole: {info.damaged[0]}")
    scene = Scene(session_robot(info.parts[0]), base_to_tracker)
    # as the session writer makes them, from whole parts: every stepper report kept to hold angles from
    stream = SceneStream(scene, rate_hz, stepper_history=None)
    batches: list[Batch] = []
    for part in info.parts:
        streams = read_fixed_topics(part)
        for topic in (T.STEPPER, stream.joint_topic, T.TRACKER):
            if topic in streams:
                batches += stream.feed(topic, streams[topic].log_time, streams[topic].rows)
    batches += stream.finish()
    start = min((int(b.log_time[0]) for b in batches if len(b)), default=0)
    batches = scene.static(start) + batches
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    try:
        with ExitStack() as stack:
            sources = [stack.enter_context(as_path(p).open("rb")) for p in info.parts]
            with open(partial, "wb") as f:
                urdf = [(URDF_ATTACHMENT, "application/xml", scene.urdf.encode())]
                # the session's own standard topics (a recording writes them) are made again, tracker placed
                n = merge_with(sources, f, "vslab sessions export", batches, urdf, replace=STANDARD_TOPICS)
        partial.replace(out)
    finally:  # whatever stopped it (a damaged part, a full disk, ^C): no half file is left behind
        partial.unlink(missing_ok=True)
    return n
