"""What the processes of a recording and of batch work do about the scheduler and their parent
(acquisition/processes.py), checked in real child processes."""

from __future__ import annotations

import ctypes
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import psutil
import pytest

from acquisition import processes

ROOT = Path(__file__).resolve().parents[1]
LINUX = sys.platform.startswith("linux")

BATCH_JOB = textwrap.dedent(
    """
    import os, subprocess, sys, time
    from acquisition.processes import lower_priority
    started = os.getpid()
    lower_priority()
    try:  # empty where the kernel does not group this process by session (a container's cgroup)
        group = (open("/proc/self/autogroup").read().split() or ["-"])[-1]
    except OSError:
        group = "-"
    worker = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # like a pool worker
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    print(started, os.getpid(), os.getsid(0), nice, group, worker.pid, flush=True)
    if sys.argv[1] == "exit":
        sys.exit(3)
    time.sleep(60)
    """
)


def _batch_job(mode: str, nice: int = 19) -> subprocess.Popen:
    env = {**os.environ, "VSLAB_BATCH_NICE": str(nice), "PYTHONPATH": str(ROOT)}
    # process_group=0: the job leads its own process group, as a shell's job does
    command = [sys.executable, "-c", BATCH_JOB, mode]
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, text=True, process_group=0)


def _fields(proc: subprocess.Popen) -> tuple[int, int, int, int, str, int]:
    started, pid, sid, nice, group, worker = proc.stdout.readline().split()
    return int(started), int(pid), int(sid), int(nice), group, int(worker)


def _gone(*pids: int, within_s: float = 5.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        alive = [
            p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
        ]
        if not alive:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.skipif(not LINUX, reason="sessions and autogroups are Linux's")
def test_batch_work_runs_niced_in_a_session_of_its_own_and_exits_with_its_status():
    proc = _batch_job("exit")
    started, pid, sid, nice, group, _ = _fields(proc)
    assert proc.wait(timeout=30) == 3  # the job's own exit status comes through the waiting parent
    assert pid != started and sid == pid  # the job went on in a child that leads a new session
    assert nice == 19
    if group != "-":  # where the kernel groups by session, the job's group is lowered too
        assert group == "19"
        # the session it came from is untouched
        assert _own_group_nice() in ("0", "-")


def _own_group_nice() -> str:
    try:
        return (Path("/proc/self/autogroup").read_text().split() or ["-"])[-1]
    except OSError:
        return "-"


def _signals_and_cpu(*pids: int) -> str:
    """What each process was doing: its state, the signals it blocks and ignores, its CPU time so far."""
    lines = []
    for pid in pids:
        try:
            status = dict(
                line.split(":\t", 1)
                for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                if ":\t" in line
            )
            ran_ns = Path(f"/proc/{pid}/schedstat").read_text().split()[0]
        except OSError:
            lines.append(f"{pid}: gone")
            continue
        fields = ("State", "SigBlk", "SigIgn", "SigCgt")
        lines.append(
            f"{pid}: " + ", ".join(f"{k} {status.get(k, '?').strip()}" for k in fields) + f", ran {ran_ns} ns"
        )
    return "; ".join(lines)


@pytest.mark.skipif(not LINUX, reason="sessions and autogroups are Linux's")
def test_ctrl_c_reaches_the_batch_job_and_a_killed_parent_takes_it_along():
    # nice 1: how signals pass is what is checked here; at nice 19 the job's session gets ~1.5 % of a core
    # beside CPU-bound work (its Ctrl-C took 0.9 s to end it under bench/load.py, against 0.05 s idle)
    proc = _batch_job("sleep", nice=1)
    _, child, _, _, _, worker = _fields(proc)
    proc.send_signal(signal.SIGINT)  # what the terminal sends to its foreground group
    try:
        code = proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the job did not end within 30 s of Ctrl-C: {_signals_and_cpu(proc.pid, child, worker)}")
    assert code == 128 + signal.SIGINT
    assert _gone(child, worker), "Ctrl-C did not reach the job's whole group"

    proc = _batch_job("sleep", nice=1)
    _, child, _, _, _, worker = _fields(proc)
    proc.kill()
    proc.wait(timeout=30)
    assert _gone(child, worker), "the batch job (or its worker) outlived its killed parent"


def test_batch_nice_zero_leaves_the_process_as_it_is(monkeypatch):
    monkeypatch.setenv("VSLAB_BATCH_NICE", "0")
    before = (os.getpid(), os.getpriority(os.PRIO_PROCESS, 0))
    processes.lower_priority()
    assert (os.getpid(), os.getpriority(os.PRIO_PROCESS, 0)) == before


def _slice_ns() -> int:
    libc = ctypes.CDLL(None, use_errno=True)
    buf = ctypes.create_string_buffer(56)
    assert libc.syscall({"x86_64": 315, "aarch64": 275}[os.uname().machine], 0, buf, 56, 0) == 0
    return struct.unpack("IIQiIQQQII", buf.raw)[5]


@pytest.mark.skipif(
    not LINUX or os.uname().machine not in ("x86_64", "aarch64")
    or tuple(int(x) for x in os.uname().release.split(".")[:2]) < (6, 12),
    reason="custom slices of the fair scheduler are Linux >= 6.12",
)  # fmt: skip
def test_unprivileged_elevation_asks_for_a_short_slice():
    code = textwrap.dedent(
        """
        import os
        os.environ["VSLAB_RT_PRIORITY"] = "0"
        from acquisition.processes import elevate
        from tests.test_processes import _slice_ns
        print(elevate(), _slice_ns())
        """
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.split()[-3:] == ["ms", "slice", str(processes.SHORT_SLICE_NS)]
