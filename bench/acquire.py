"""Acquisition under load: the VSL rig recorded by the daemons, with the computer busy or idle.

Starts the rig (the twin behind its devices' emulators), records every device through the supervisor, its
daemons and the writer for ``--seconds``, and prints per stream: the rate achieved (from the file), samples
expected and lost (the recorder's account, checked against the file), the p99 period jitter
(|Δt − 1/rate| between consecutive host stamps) and the longest gap. The machine's load is printed before
and during the run, and whether the daemons got a real-time priority (``--no-elevate`` runs them as any
user would without the privilege: the targets must hold that way too).

Loads (``--load``): ``none``; ``train``, a `vslab train` grid (a small simulated campaign is built first in a
temporary lab; the grid is run with new seeds again and again, one worker per core, the way `vslab train`
runs: at batch priority); ``cpu``, one busy loop per core at the ordinary priority (the worst case: other
people's programs that do not yield).

Targets (issue "acquisition daemons"): the servo bus at the description's rate sustained (1000 Hz then; 400 Hz
once the rig kept the wire's timing: 1 Mbaud behind a 1 ms latency timer carries 588 Sync Reads a second,
issue 31; 300 Hz since the host's own time per read left 400 Hz 4 % of each slot; 250 Hz since 300 Hz lost
samples where a hypervisor took a tenth of the CPUs), 0 lost samples in every
stream, p99 period jitter < 1 ms, with ``--load train`` and ``--load none``; ``--rate servo_bus=HZ`` reports
what a rate reaches (the recorder refuses one above the link's ceiling: ``bench/bus.py`` measures the ceiling
itself).

Usage: python bench/acquire.py [--seconds S] [--load none|train|cpu] [--rate DEVICE=HZ]... [--no-elevate]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from acquisition.recorder.recorder import Recorder
from acquisition.schemas import topics as T
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.session_card import readable_parts
from models.robot import load_robot
from twin.ptyhost import wait_for_ports

ROOT = Path(__file__).resolve().parents[1]

STREAMS = {T.SERVO_STATE: "servo_bus", T.PRESSURE: "pressure_board", T.STEPPER: "stepper_board",
           T.TRACKER: "tracker"}  # fmt: skip


def cpu_load(stack: contextlib.ExitStack) -> None:
    """One busy loop per core at the ordinary priority."""
    for _ in range(os.cpu_count() or 1):
        proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        stack.callback(proc.kill)


def train_load(stack: contextlib.ExitStack, seconds: float) -> None:
    """`vslab train` grids, one after the other, on a small simulated campaign (built first)."""
    lab = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-acq-lab-")))
    vslab = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "--quiet"]
    env = {k: v for k, v in os.environ.items() if k != "VSLAB_BATCH_NICE"}
    print("  preparing the training load: a 3000-point campaign and its dataset …", flush=True)
    subprocess.run([*vslab, "simulate", "campaign", "--set", "points=3000"], check=True, cwd=ROOT, env=env,
                   stdout=subprocess.DEVNULL)  # fmt: skip
    subprocess.run([*vslab, "build", "--name", "campaign"], check=True, cwd=ROOT, env=env,
                   stdout=subprocess.DEVNULL)  # fmt: skip
    script = (
        "import subprocess, sys, itertools\n"
        "for k in itertools.count():\n"
        f"    seeds = '[' + ','.join(str(100 * k + i) for i in range(100)) + ']'\n"
        f"    subprocess.run({vslab!r} + ['train', '--set', 'seeds=' + seeds, '--set', 'max_epochs=40'],"
        " stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=env, start_new_session=True)
    stack.callback(lambda: os.killpg(proc.pid, 9))
    time.sleep(5.0)  # the grid is training when the recording starts


def stream_figures(parts: list[Path], final: dict, rates: dict[str, float]) -> list[str]:
    data: dict = {}
    for part in parts:
        for topic, td in read_fixed_topics(part).items():
            data.setdefault(topic, []).append(td.log_time)
    lines = []
    for topic, device in STREAMS.items():
        t = np.sort(np.concatenate(data.get(topic, [np.zeros(0, np.int64)])))
        c = final[topic]
        if len(t) < 2:
            lines.append(f"  {topic:<20} no samples")
            continue
        period = 1e9 / rates[device]
        dt = np.diff(t)
        rate = (len(t) - 1) / ((t[-1] - t[0]) / 1e9)
        jitter = np.percentile(np.abs(dt - period), 99) / 1e6
        lines.append(
            f"  {topic:<20} {rate:8.1f} Hz of {rates[device]:6.0f}   expected {c['expected']:>9,}  "
            f"lost {c['lost']:>6,}  dropped {c['dropped']:>4,}  written {c['written']:>9,} (file {len(t):,}) "
            f"p99 jitter {jitter:6.3f} ms  longest gap {dt.max() / 1e6:7.1f} ms"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--load", choices=("none", "train", "cpu"), default="none")
    parser.add_argument("--rate", action="append", default=[], help="DEVICE=HZ over the robot description's")
    parser.add_argument("--no-elevate", action="store_true", help="daemons and rig at the ordinary priority")
    args = parser.parse_args()
    if args.no_elevate:
        os.environ["VSLAB_RT_PRIORITY"] = "0"
    robot = load_robot("vsl")
    rates = {name: spec.rate_hz for name, spec in robot.devices.items()}
    overrides = {k: float(v) for k, v in (r.split("=") for r in args.rate)}
    rates.update(overrides)
    print(f"acquisition bench: VSL rig, {args.seconds:.0f} s, load {args.load}, rates "
          f"{json.dumps(rates)}, {os.cpu_count()} cores, load average before {os.getloadavg()}")  # fmt: skip
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-acq-")))
        if args.load == "cpu":
            cpu_load(stack)
        elif args.load == "train":
            train_load(stack, args.seconds)
        rig = subprocess.Popen([sys.executable, "-m", "twin.rig", "--robot", "vsl", "--run-dir",
                                str(tmp / "run"), "--parent-pid", str(os.getpid())], cwd=ROOT)  # fmt: skip
        stack.callback(lambda: (rig.terminate(), rig.wait()))
        ports = wait_for_ports(tmp / "run", timeout_s=60)
        rig_cpu0 = _cpu_s(rig.pid)
        with Recorder(robot, ports, tmp / "s", "bench", rates=overrides) as rec:
            priorities = rec.priorities()
            time.sleep(args.seconds)
            during = os.getloadavg()
        rig_cpu = _cpu_s(rig.pid) - rig_cpu0
        lines = stream_figures(readable_parts(tmp / "s"), rec.final, rates)
    print(f"  load average during {during}; daemons at {sorted(set(priorities.values()))}; rig CPU "
          f"{100 * rig_cpu / args.seconds:.0f} % of a core; restarts {rec.restarts or 'none'}")  # fmt: skip
    print("\n".join(lines))


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    main()
