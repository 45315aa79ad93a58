"""Cost of the rig (the twin behind the device emulators on ptys): CPU while idle and per Dynamixel Sync Read.

    .venv/bin/python bench/rig.py [--seconds S] [--rate HZ]

Starts the rig for robot vsl in its own process (as ``vslab rig`` does) and reads its CPU time and wake-ups
from /proc (no extra dependency), over S seconds each:
  idle      no client at all: % of a core, wake-ups/s (voluntary context switches);
  sync read Sync Reads of the bus's servos through the real driver (``ServoBus`` on dynamixel-sdk), back to
            back and paced at --rate: requests/s, round trip p50/p99, the rig's CPU µs per request;
  + boards  the same while the pressure board streams at 250 Hz and the stepper board at 100 Hz to a second
            client process (as the recorder's daemons would): the streams' rates and sequence gaps too.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.devices.servo_bus import ServoBus
from models.robot import load_robot
from twin.ptyhost import wait_for_ports

PRESSURE_HZ, STEPPER_HZ = 250, 100
_CLK_TCK = os.sysconf("SC_CLK_TCK")


# ------------------------------------------------------------------------------------------ /proc readings
def cpu_ns(pid: int) -> int:
    """CPU time (ns) of every thread of ``pid`` so far: schedstat (ns) if the kernel has it, else stat."""
    total = 0
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/schedstat") as f:
                total += int(f.read().split()[0])
        return total
    except (FileNotFoundError, ProcessLookupError, IndexError, ValueError):
        pass
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) * 1_000_000_000 // _CLK_TCK  # utime + stime, in ticks


def wakeups(pid: int) -> int:
    """Voluntary context switches of every thread of ``pid`` (each one is a sleep, then a wake-up)."""
    total = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/status") as f:
                for line in f:
                    if line.startswith("voluntary_ctxt_switches"):
                        total += int(line.split()[1])
        except FileNotFoundError:  # a thread that ended meanwhile
            continue
    return total


def scheduling(pid: int) -> str:
    """The rig's scheduling class and priority (it asks for a real-time one where it may)."""
    try:
        policy = os.sched_getscheduler(pid)
    except OSError:
        return "scheduling unknown"
    if policy == os.SCHED_FIFO:
        return f"SCHED_FIFO {os.sched_getparam(pid).sched_priority}"
    return f"nice {os.getpriority(os.PRIO_PROCESS, pid)}"


@dataclass
class Usage:
    """What the rig spent over one measurement."""

    wall_s: float
    cpu_s: float
    wakeups: int

    @property
    def core_pct(self) -> float:
        return 100.0 * self.cpu_s / self.wall_s


class Meter:
    """``with Meter(pid) as m: ...`` then ``m.usage``."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.usage: Usage | None = None

    def __enter__(self) -> Meter:
        self._t, self._cpu, self._wake = time.perf_counter(), cpu_ns(self.pid), wakeups(self.pid)
        return self

    def __exit__(self, *exc: object) -> None:
        self.usage = Usage(
            time.perf_counter() - self._t,
            (cpu_ns(self.pid) - self._cpu) * 1e-9,
            wakeups(self.pid) - self._wake,
        )


# ------------------------------------------------------------------------------------------------ clients
@dataclass
class ReadRun:
    """Sync Reads done by the client: count, round trips (s), the client's own CPU (s)."""

    n: int
    wall_s: float
    rtt_s: np.ndarray
    client_cpu_s: float


def sync_reads(bus: ServoBus, seconds: float, rate_hz: float | None) -> ReadRun:
    """Sync Reads for ``seconds``, back to back (``rate_hz`` None) or paced on absolute deadlines."""
    rtt = []
    period = 1.0 / rate_hz if rate_hz else 0.0
    cpu0, start = time.process_time(), time.perf_counter()
    end = start + seconds
    due = start
    while (t := time.perf_counter()) < end:
        if period:
            if due > t:
                time.sleep(due - t)
            elif t - due > period:  # fell behind by more than a period: do not burst to catch up
                due = t
            due += period
        t0 = time.perf_counter()
        bus.read_state()
        rtt.append(time.perf_counter() - t0)
    wall = time.perf_counter() - start
    return ReadRun(len(rtt), wall, np.array(rtt), time.process_time() - cpu0)


def board_client(ports: dict[str, str], ready, stop, results) -> None:
    """Second client process: stream both boards, drain them every 10 ms, report rates and seq gaps."""
    from acquisition.devices.boards import PressureBoard, StepperBoard

    out = {}
    with PressureBoard(ports["pressure_board"]) as pb, StepperBoard(ports["stepper_board"]) as sb:
        boards = {"pressure_board": (pb, PRESSURE_HZ), "stepper_board": (sb, STEPPER_HZ)}
        samples: dict[str, list] = {name: [] for name in boards}
        for board, hz in boards.values():
            board.start_stream(hz)
        time.sleep(0.2)
        for board, _ in boards.values():
            board.read_samples()  # start counting from a running stream
        ready.set()
        start = time.perf_counter()
        while not stop.is_set():
            time.sleep(0.01)
            for name, (board, _) in boards.items():
                samples[name] += board.read_samples()
        wall = time.perf_counter() - start
        for name, (board, hz) in boards.items():
            board.stop_stream()
            got = samples[name]
            seq = np.array([s.seq for s in got], dtype=np.int64)
            micros = np.array([s.micros for s in got], dtype=np.int64)
            span_us = int(np.sum(np.diff(micros) % (1 << 32))) if len(got) > 1 else 0
            out[name] = {
                "rate_hz": hz,
                "n": len(got),
                "host_hz": len(got) / wall,
                "board_hz": (len(got) - 1) / (span_us * 1e-6) if span_us else 0.0,
                "seq_gaps": int(np.sum(np.diff(seq) != 1)),
            }
    results.put(out)


class Boards:
    """The board client process, streaming from ``__enter__`` to ``__exit__``."""

    def __init__(self, ports: dict[str, str]) -> None:
        ctx = mp.get_context("spawn")
        self.ready, self.stop, self.results = ctx.Event(), ctx.Event(), ctx.Queue()
        self.proc = ctx.Process(target=board_client, args=(ports, self.ready, self.stop, self.results))
        self.report: dict | None = None

    def __enter__(self) -> Boards:
        self.proc.start()
        if not self.ready.wait(30):
            self.proc.terminate()
            raise RuntimeError("the board client did not start streaming")
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.report = self.results.get(timeout=30)
        self.proc.join(10)


# ------------------------------------------------------------------------------------------------- report
def show_usage(label: str, use: Usage) -> None:
    print(f"  {label:34s}: {use.core_pct:6.2f} % of a core   {use.wakeups / use.wall_s:7.0f} wake-ups/s")


def show_reads(label: str, run: ReadRun, use: Usage, baseline_pct: float | None = None) -> None:
    p50, p99 = np.percentile(run.rtt_s * 1e6, [50, 99])
    per_req = use.cpu_s / run.n * 1e6 if run.n else float("nan")
    line = (
        f"  {label:34s}: {run.n / run.wall_s:7.0f} req/s   rtt p50 {p50:6.0f} µs  p99 {p99:6.0f} µs   "
        f"rig {per_req:5.0f} µs CPU/req ({use.core_pct:5.1f} % core)   "
        f"client {run.client_cpu_s / run.n * 1e6:4.0f} µs CPU/req"
    )
    if baseline_pct is not None and run.n:
        net = (use.cpu_s - baseline_pct / 100.0 * use.wall_s) / run.n * 1e6
        line += f"   [{net:4.0f} µs/req beyond streaming]"
    print(line)


def show_streams(report: dict) -> None:
    for name, r in report.items():
        print(
            f"    {name:16s} {r['rate_hz']:3d} Hz asked: {r['host_hz']:6.1f} Hz received (host), "
            f"{r['board_hz']:6.1f} Hz on the board clock, {r['seq_gaps']} seq gaps in {r['n']} lines"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="length of each measurement")
    parser.add_argument("--rate", type=float, default=1000.0, help="paced Sync Read rate (Hz)")
    parser.add_argument("--no-boards", action="store_true", help="skip the runs with the boards streaming")
    parser.add_argument(
        "--rig-root",
        type=Path,
        help="run the rig from this source tree instead (e.g. an older revision, unpacked by git archive)",
    )
    args = parser.parse_args()
    seconds = args.seconds
    robot = load_robot("vsl")
    ids = sorted(robot.devices["servo_bus"].ids.values())
    load1, load5, load15 = os.getloadavg()
    print(
        f"machine: {os.cpu_count()} CPUs, load average {load1:.2f} / {load5:.2f} / {load15:.2f} (1/5/15 min)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "rig"
        env, cwd = None, None
        if args.rig_root is not None:  # the rig's own imports come from there; the client stays ours
            cwd = args.rig_root.resolve()
            env = {**os.environ, "PYTHONPATH": str(cwd)}
            print(f"rig from {cwd}")
        rig = subprocess.Popen(
            [sys.executable, "-m", "twin.rig", "--robot", "vsl", "--run-dir", str(run_dir)],
            cwd=cwd,
            env=env,
        )
        try:
            ports = wait_for_ports(run_dir, timeout_s=60)
            time.sleep(1.0)  # let start-up work (imports, JIT cache loads) finish
            print(f"rig for vsl, pid {rig.pid} ({scheduling(rig.pid)}), servos {ids}, {seconds:g} s each")
            with Meter(rig.pid) as idle:
                time.sleep(seconds)
            show_usage("idle (no client)", idle.usage)
            with ServoBus(ports["servo_bus"], ids=ids) as bus:
                bus.configure()
                bus.set_torque(True)
                sync_reads(bus, 0.5, None)  # warm up both sides
                for label, rate in (
                    ("sync read, back to back", None),
                    (f"sync read at {args.rate:g} Hz", args.rate),
                ):
                    with Meter(rig.pid) as m:
                        run = sync_reads(bus, seconds, rate)
                    show_reads(label, run, m.usage)
                if not args.no_boards and {"pressure_board", "stepper_board"} <= ports.keys():
                    with Boards(ports) as boards, Meter(rig.pid) as m:
                        time.sleep(seconds)
                    show_usage(f"boards streaming {PRESSURE_HZ}+{STEPPER_HZ} Hz only", m.usage)
                    show_streams(boards.report)
                    streaming_pct = m.usage.core_pct
                    for label, rate in (
                        ("+ boards, sync read back to back", None),
                        (f"+ boards, sync read at {args.rate:g} Hz", args.rate),
                    ):
                        with Boards(ports) as boards, Meter(rig.pid) as m:
                            run = sync_reads(bus, seconds, rate)
                        show_reads(label, run, m.usage, streaming_pct)
                        show_streams(boards.report)
        finally:
            rig.terminate()
            rig.wait(timeout=10)


if __name__ == "__main__":
    main()
