"""Run a command while every core is busy: one CPU-bound process per core at the ordinary priority.

    python bench/load.py [--per-core N] [--steal F] -- COMMAND ...   (make test-under-load: the suite)

The real-time code must hold on a busy lab computer, so its tests must pass under this load too. The load
processes are plain busy loops (other people's programs that never yield), stopped when the command ends;
the command's exit code is returned, with the load average it ran under.

``--steal F`` also takes a share F of each CPU from everything, real-time processes included, in short
slices (``--slice-ms``, default 3 ms): a process held on each CPU at the highest real-time priority that
spins a slice and sleeps the rest. That is what a busy hypervisor does to a virtual machine (CI's host took
15–20 % of both CPUs during recordings, in slices: no CPU stopped for more than 7 ms at once), which
ordinary load cannot reproduce, as the real-time daemons run before it. Needs real-time priority (root or
CAP_SYS_NICE); without it the command is not run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-core", type=int, default=1, help="busy processes per core")
    parser.add_argument("--steal", type=float, default=0.0, help="share of each CPU taken in slices (0–0.5)")
    parser.add_argument("--slice-ms", type=float, default=3.0, help="length of one stolen slice (ms)")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give a command to run under load, after --")
    if not 0.0 <= args.steal <= 0.5 or args.slice_ms <= 0:
        parser.error("--steal takes a share from 0 to 0.5, --slice-ms a positive length")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range((os.cpu_count() or 1) * args.per_core)]  # fmt: skip
    if args.steal > 0:
        thieves = [_thief(cpu, args.steal, args.slice_ms / 1e3) for cpu in sorted(os.sched_getaffinity(0))]
        hogs += thieves
        time.sleep(0.5)
        if any(t.poll() is not None for t in thieves):
            for hog in hogs:
                hog.kill()
            print("load.py: --steal needs real-time priority (SCHED_FIFO), which this user may not take")
            return 2
    start = time.monotonic()
    try:
        code = subprocess.call(command)
    finally:
        load = os.getloadavg()
        for hog in hogs:
            hog.kill()
            hog.wait()
    stolen = f", {args.steal:.0%} of each CPU taken in {args.slice_ms:g} ms slices" if args.steal else ""
    print(
        f"load.py: {len(hogs)} busy processes on {os.cpu_count()} cores{stolen}, "
        f"{time.monotonic() - start:.0f} s; "
        f"load average at the end {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; exit {code}"
    )
    return code


_THIEF = """
import os, sys, time
cpu, share, slice_s = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
os.sched_setaffinity(0, {cpu})
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(os.sched_get_priority_max(os.SCHED_FIFO)))
rest_s = slice_s * (1 - share) / share
while True:
    end = time.perf_counter() + slice_s
    while time.perf_counter() < end:
        pass
    time.sleep(rest_s)
"""


def _thief(cpu: int, share: float, slice_s: float) -> subprocess.Popen:
    """A process that takes ``share`` of CPU ``cpu`` from everything, in slices of ``slice_s``."""
    return subprocess.Popen([sys.executable, "-c", _THIEF, str(cpu), str(share), str(slice_s)])


if __name__ == "__main__":
    sys.exit(main())
