"""POPUP's CAN bus on the rig: frames per second through slcan, the PDO loop rate achieved, the bus load.

    python bench/can_bus.py [--seconds 10] [--rate 100 200 500]

(Not bench/can.py: a script of that name would shadow python-can's ``can`` package, as a bench script
named after any package it imports would.)

Starts the POPUP rig (its own process, as on the bench), opens the three CiA 402 drives with python-can's
slcan interface and canopen, enables them and runs the PDO loop at each SYNC rate: every cycle one SYNC, the
drives' two TPDOs each and one target-position RPDO per drive; a SYNC waits for late answers up to a period
past its slot, as the recorder's. First prints the load the description's rates put on the bus, computed
(``can_budget.popup_can_load``: per frame kind, worst case and typical); then per rate the cycles run and
answered by every drive, the frames per second through the adapter (both directions), the loop's period
jitter, the bus load the rig's bus measured (bits carried / bit rate / seconds, stuff bits included) and the
frames it lost on full transmit queues; and what the rig itself cost (% of a core, wake-ups/s), idle with
the adapter closed and during each rate: a real arm costs the host nothing, so the twin's cost is taken
from the recorder's daemons. States the machine's load as it ran.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rig import Meter, scheduling  # bench/rig.py: the rig process's CPU and wake-ups from /proc

from acquisition.devices.can_budget import popup_can_load
from acquisition.devices.can_drives import CanDrives
from models.robot import load_robot
from twin.ptyhost import send_control, wait_for_ports


def run_rate(drives: CanDrives, run_dir: Path, rate_hz: float, seconds: float) -> dict:
    period = 1.0 / rate_hz
    before = send_control(run_dir, {"op": "can"})
    start = time.monotonic()
    next_t, stamps, answered, cycles = start, [], 0, 0
    goal = None
    while time.monotonic() - start < seconds:
        cycle = drives.sync(wait_s=2 * period)  # as the recorder: late answers waited for, a period past
        stamps.append(time.monotonic())
        if cycle is not None:
            cycles += 1
            answered += bool(cycle.answered.all())
            if goal is None and cycle.answered.all():
                goal = cycle.position_rad.copy()
        if goal is not None:
            drives.write_goals(goal)
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    elapsed = time.monotonic() - start
    after = send_control(run_dir, {"op": "can"})
    frames = after["frames"] - before["frames"]
    busy = after["busy_s"] - before["busy_s"]
    lost = after["lost"] - before["lost"]
    bus_s = after["t"] - before["t"]
    dt = np.diff(stamps) * 1e3
    return {"rate": rate_hz, "cycles": cycles, "answered": answered, "loop_hz": len(stamps) / elapsed,
            "frames_s": frames / bus_s, "load": busy / bus_s, "lost": lost, "dt_p50": np.median(dt),
            "dt_p99": np.percentile(dt, 99)}  # fmt: skip


def print_computed_load(robot) -> None:
    """The bus load of the description's configured rates, per frame kind and in all."""
    load = popup_can_load(robot)
    print(f"computed at {load['bitrate'] / 1e6:g} Mbit/s, SYNC {load['sync_hz']:g} Hz:")
    print(f"{'frame':>17} {'bytes':>5} {'frames/s':>9} {'worst':>7} {'typical':>8}")
    for r in load["rows"]:
        print(f"{r['frame']:>17} {r['bytes']:5d} {r['frames_per_s']:9.0f} {r['load_worst']:7.2%} "
              f"{r['load_typical']:8.2%}")  # fmt: skip
    t = load["total"]
    print(f"{'total':>17} {'':5} {t['frames_per_s']:9.0f} {t['load_worst']:7.2%} {t['load_typical']:8.2%}"
          f"   (to the host: {t['slcan_bytes_per_s'] / 1e3:.1f} kB/s of slcan lines)")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate", type=float, nargs="+", default=[100.0, 200.0, 500.0])
    args = parser.parse_args()
    robot = load_robot("popup")
    spec = robot.devices["can_bus"]
    load1, load5, _ = os.getloadavg()
    drives = f"{len(spec.ids)} CiA 402 drives, {spec.baud / 1e6:g} Mbit/s"
    print(f"POPUP CAN bus on the rig: {drives}, slcan over a pty")
    print(f"machine: {os.cpu_count()} cores, load average {load1:.2f} (1 min) {load5:.2f} (5 min) at start")
    print_computed_load(robot)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp)
        rig = subprocess.Popen([sys.executable, "-m", "twin.rig", "--robot", "popup", "--run-dir", tmp])
        try:
            port = wait_for_ports(run_dir)["can_bus"]
            time.sleep(1.0)  # start-up work (imports, JIT cache loads) done
            with Meter(rig.pid) as idle:
                time.sleep(min(args.seconds, 5.0))
            use = idle.usage
            print(
                f"rig ({scheduling(rig.pid)}) idle, adapter closed (the boards stream, no host reads): "
                f"{use.core_pct:.1f} % of a core, {use.wakeups / use.wall_s:.0f} wake-ups/s"
            )
            limits = {j.name: (j.lower_rad, j.upper_rad) for j in robot.joints}
            with CanDrives(port, spec.ids, limits_rad=limits, bitrate=spec.baud) as drives:
                drives.enable()
                print(f"{'SYNC Hz':>8} {'loop Hz':>8} {'cycles':>7} {'all answered':>13} {'frames/s':>9} "
                      f"{'bus load':>9} {'lost':>5} {'period p50/p99 ms':>18} "
                      f"{'rig % core':>11}")  # fmt: skip
                for rate in args.rate:
                    with Meter(rig.pid) as m:
                        r = run_rate(drives, run_dir, rate, args.seconds)
                    print(f"{r['rate']:8.0f} {r['loop_hz']:8.1f} {r['cycles']:7d} "
                          f"{r['answered'] / max(r['cycles'], 1):13.1%} {r['frames_s']:9.0f} "
                          f"{r['load']:9.1%} {r['lost']:5d} "
                          f"{r['dt_p50']:8.2f} / {r['dt_p99']:6.2f} {m.usage.core_pct:11.1f}")  # fmt: skip
        finally:
            rig.terminate()
            rig.wait(timeout=10)
    load1, _, _ = os.getloadavg()
    print(f"load average {load1:.2f} (1 min) at the end")


if __name__ == "__main__":
    main()
