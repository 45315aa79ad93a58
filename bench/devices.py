"""Device throughput against the rig (the twin in real time behind emulators on ptys).

Prints the sustained Sync Read rate of the two servos through the real dynamixel-sdk (target ≥ 500 Hz) with
latency percentiles, and the tracker's frame rate (40 Hz expected) when the rig serves a tracker.
Usage: python bench/devices.py [--seconds S]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from acquisition.devices.servo_bus import ServoBus
from models.robot import load_robot
from twin.ptyhost import wait_for_ports


def servo_rate(port: str, ids: list[int], seconds: float) -> tuple[float, np.ndarray]:
    """Back-to-back Sync Reads for ``seconds``: (reads per second, per-read latency in s)."""
    with ServoBus(port, ids=ids) as bus:
        bus.configure()
        bus.set_torque(True)
        latencies = []
        end = time.perf_counter() + seconds
        while (start := time.perf_counter()) < end:
            bus.read_state()
            latencies.append(time.perf_counter() - start)
    lat = np.array(latencies)
    return len(lat) / lat.sum(), lat


def tracker_rate(port: str, seconds: float) -> float | None:
    """Distinct tracker frames per second, if a tracker driver is available."""
    try:
        from acquisition.devices.tracker import Tracker
    except ImportError:
        return None
    frames = set()
    with Tracker(port) as trk:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            frames.add(trk.read().frame)
    return (max(frames) - min(frames)) / seconds if len(frames) > 1 else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    robot = load_robot("vsl")
    ids = [robot.devices["servo_bus"].ids[q] for q in ("q2", "q3")]
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "rig"
        rig = subprocess.Popen(
            [sys.executable, "-m", "twin.rig", "--robot", "vsl", "--run-dir", str(run_dir)]
        )
        try:
            ports = wait_for_ports(run_dir, timeout_s=60)
            rate, lat = servo_rate(ports["servo_bus"], ids, args.seconds)
            p50, p90, p99, pmax = np.percentile(lat * 1e3, [50, 90, 99, 100])
            print("devices against the rig (real dynamixel-sdk, pty)")
            print(f"  servo Sync Read, 2 servos : {rate:7.0f} Hz sustained   (target >= 500 Hz)")
            print(
                f"  Sync Read latency (ms)    : p50 {p50:.2f}  p90 {p90:.2f}  p99 {p99:.2f}  max {pmax:.2f}"
            )
            if "tracker" in ports:
                frames = tracker_rate(ports["tracker"], args.seconds)
                if frames is not None:
                    print(f"  tracker frames            : {frames:7.1f} Hz   (40 Hz expected)")
        finally:
            rig.terminate()
            rig.wait(timeout=10)


if __name__ == "__main__":
    main()
