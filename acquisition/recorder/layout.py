"""The shared layout of one recording: which processes there are and the files they meet in.

The supervisor writes it (``layout.json`` in the recording's run directory on tmpfs) before it starts
anything; every daemon and the writer read it. It names the session, the robot description, the clocks
(the slot origin every polled daemon counts from, and the offset from the monotonic clock to UNIX time),
each device's driver, port, rate and topics, and the ring and status files.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

LAYOUT_FILE = "layout.json"
SUPERVISOR = "supervisor"  # the events ring the supervisor (and the plan runner) writes


@dataclass
class DeviceEntry:
    name: str
    driver: str
    port: str
    rate_hz: float
    topics: list[str]  # every topic the device writes
    sampled: list[str]  # of which: sampled streams (counted against their sequence numbers)
    sampled_rates_hz: dict[str, float] = field(default_factory=dict)  # each one's rate (default: rate_hz)


@dataclass
class Layout:
    run_dir: Path
    session_dir: Path
    session_id: str
    experiment: str
    robot_json: str
    parent_pid: int
    t0_ns: int  # monotonic ns: slot 0 of every polled device
    unix_offset_ns: int  # log_time = monotonic ns + this
    devices: dict[str, DeviceEntry] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)
    batch_s: float = 0.05  # the writer drains the rings this often …
    flush_s: float = 0.1  # … and makes what it wrote durable this often
    rotate_bytes: int | None = 512 * 1024**2
    rotate_seconds: float | None = None
    stale_s: float = 0.5  # a device silent this long is reconnected

    @staticmethod
    def new_run_dir(session_id: str) -> Path:
        """A fresh directory on tmpfs (``/dev/shm`` where there is one) for this recording's rings."""
        base = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in session_id)[:64]
        path = base / f"vslab-{os.getpid()}-{safe}"
        path.mkdir(parents=True, exist_ok=False)
        return path

    def ring(self, topic: str) -> Path:
        return self.run_dir / f"{topic.strip('/').replace('/', '.')}.ring"

    def events(self, producer: str) -> Path:
        return self.run_dir / f"events.{producer}.ring"

    def status(self, process: str) -> Path:
        return self.run_dir / f"{process}.status"

    def log(self, process: str) -> Path:
        return self.session_dir / "logs" / f"{process}.log"

    @property
    def producers(self) -> list[str]:
        """Who writes events: the supervisor and every device daemon."""
        return [SUPERVISOR, *self.devices]

    def save(self) -> Path:
        path = self.run_dir / LAYOUT_FILE
        data = asdict(self)
        data["run_dir"], data["session_dir"] = str(self.run_dir), str(self.session_dir)
        path.write_text(json.dumps(data))
        return path

    @classmethod
    def load(cls, path: Path) -> Layout:
        data = json.loads(Path(path).read_text())
        data["run_dir"], data["session_dir"] = Path(data["run_dir"]), Path(data["session_dir"])
        data["devices"] = {name: DeviceEntry(**d) for name, d in data["devices"].items()}
        return cls(**data)
