"""Run a command while every core is busy: one CPU-bound process per core at the ordinary priority.

    python bench/load.py [--per-core N] -- COMMAND ...      (make test-under-load runs the suite this way)

The real-time code must hold on a busy lab computer, so its tests must pass under this load too. The load
processes are plain busy loops (other people's programs that never yield), stopped when the command ends;
the command's exit code is returned, with the load average it ran under.
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
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give a command to run under load, after --")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range((os.cpu_count() or 1) * args.per_core)]  # fmt: skip
    start = time.monotonic()
    try:
        code = subprocess.call(command)
    finally:
        load = os.getloadavg()
        for hog in hogs:
            hog.kill()
            hog.wait()
    print(
        f"load.py: {len(hogs)} busy processes on {os.cpu_count()} cores, {time.monotonic() - start:.0f} s; "
        f"load average at the end {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; exit {code}"
    )
    return code


if __name__ == "__main__":
    sys.exit(main())
