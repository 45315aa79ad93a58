"""What a process of a recording does about its parent and the scheduler.

- ``die_with_parent``: a daemon, the writer and the rig end when the process that started them dies, even by
  SIGKILL (Linux ``PR_SET_PDEATHSIG``, checked against the parent's pid to close the race at start-up; a
  caller also polls :func:`parent_alive` where the signal is not available).
- ``elevate``: real-time work asks for a real-time scheduling class where the OS allows it (``SCHED_FIFO``,
  else a negative nice value) and says what it got. Without the privilege it asks for what any process may
  have: a short time slice (Linux >= 6.12's EEVDF scheduler lets a task with a short slice preempt a
  CPU-bound one as soon as it wakes, instead of waiting out that task's slice of a few milliseconds).
- ``lower_priority``: batch work (training, simulation, dataset builds) yields the CPU to everything else.

On a lab PC, grant the recording user real-time priority once (as root), then log in again::

    # /etc/security/limits.d/99-vslab.conf
    @vslab  -  rtprio  40
    @vslab  -  nice    -10
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import signal
import struct
import sys
import threading
from pathlib import Path

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}  # syscall numbers (not in Python's os module)
SHORT_SLICE_NS = 100_000  # the shortest slice the kernel grants (it clamps to 0.1 ms .. 100 ms)
RT_PRIORITY = 30  # SCHED_FIFO priority of device daemons (below the kernel's own threads at 50)
ELEVATE_ENV = "VSLAB_RT_PRIORITY"  # "0": only what an unprivileged user gets (to show the targets hold so)
BATCH_NICE_ENV = "VSLAB_BATCH_NICE"  # the nice value of batch work (default 19, as `nice -n 19`; 0: as it is)


def settle_heap(collect: bool = True) -> None:
    """Collect the garbage of start-up now (``collect``) and freeze what survived (``gc.freeze``): a
    real-time loop then never pays for a full collection over the start-up heap (imports, numba, numpy:
    measured 40-80 ms, one per process some seconds in, which lost 50-80 slots of a 1 kHz servo stream).
    Later objects are collected as usual, over a small heap. Without ``collect`` only the freeze (a few
    microseconds: for a device that already streams, which a 25 ms collection would hold up)."""
    if collect:
        gc.collect()
    gc.freeze()


def die_with_parent(parent_pid: int, sig: int = signal.SIGTERM) -> None:
    """Get ``sig`` when the parent dies; exit now if it is already gone."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
        except (OSError, AttributeError) as exc:  # not fatal: parent_alive() is polled too
            log.debug("PR_SET_PDEATHSIG unavailable: %s", exc)
    if not parent_alive(parent_pid):
        os.kill(os.getpid(), sig)


def parent_alive(parent_pid: int) -> bool:
    """Whether the process that started this one is still its parent."""
    return os.getppid() == parent_pid


def _threads() -> list[int]:
    """This process's threads (Linux: each has its own scheduling; a thread started before an elevation,
    such as python-can's reader, would keep the ordinary one), or ``[0]``: the calling thread."""
    try:
        return sorted(int(tid) for tid in os.listdir("/proc/self/task"))
    except (OSError, ValueError):
        return [0]


def elevate(fifo_priority: int = RT_PRIORITY, nice: int = -10) -> str:
    """Ask for SCHED_FIFO at ``fifo_priority``, else ``nice``, and a short slice where the policy is the
    ordinary one, for every thread of this process (and so the threads they start); returns what it runs
    at. With ``VSLAB_RT_PRIORITY=0`` it asks only for what an unprivileged user gets (the short slice)."""
    got = "normal (elevation off)"
    if os.environ.get(ELEVATE_ENV, "1") != "0":
        try:
            for tid in _threads():
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(fifo_priority))
            return f"SCHED_FIFO {fifo_priority}"
        except (PermissionError, OSError, AttributeError):
            pass
        try:
            for tid in _threads():
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            got = f"nice {nice}"
        except (PermissionError, OSError):
            got = "normal (no privilege to raise it)"
    if all([short_slice(tid=tid) for tid in _threads()]):
        got += f", {SHORT_SLICE_NS / 1e6:g} ms slice"
    return got


def short_slice(slice_ns: int = SHORT_SLICE_NS, tid: int = 0) -> bool:
    """Ask the fair scheduler for a ``slice_ns`` time slice for thread ``tid`` (0: the calling one;
    ``sched_setattr`` with ``sched_runtime`` on an ordinary policy, Linux >= 6.12; no privilege needed).
    Returns whether the kernel took it."""
    number = _SYS_SCHED_SETATTR.get(os.uname().machine)
    if not sys.platform.startswith("linux") or number is None:
        return False
    # struct sched_attr: size, policy, flags, nice, priority, runtime, deadline, period, util_min, util_max
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return False
    attr = struct.pack("IIQiIQQQII", 56, 0, 0, nice, 0, slice_ns, 0, 0, 0, 0)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.syscall(number, tid, ctypes.create_string_buffer(attr, len(attr)), 0) == 0
    except (OSError, AttributeError):
        return False


def relinquish() -> None:
    """Back to the ordinary scheduling, every thread (a daemon that has stopped acquiring: its teardown, or
    its reconnecting, must not hold up the daemons still reading)."""
    for tid in _threads():
        try:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            if os.getpriority(os.PRIO_PROCESS, tid) < 0:
                os.setpriority(os.PRIO_PROCESS, tid, 0)
        except (PermissionError, OSError, AttributeError):
            pass


def lower_priority(own_session: bool = True) -> None:
    """Batch work: let acquisition and people's programs go first (this process and its children; a nice
    value cannot be raised back without privilege, so only processes that do nothing else call this).

    Where the kernel groups processes by session (``CONFIG_SCHED_AUTOGROUP``, on by default on desktop
    Linux), a process's nice value only weighs against processes of its own session: a training run in one
    terminal competes with a recording's daemons (each in a session of its own) as an equal. So the job also
    lowers its session's group. To touch nothing else of the terminal it was started from, a job that does
    not lead its own session (``own_session``) first moves into a new one: a process-group leader (a shell's
    job) cannot, so it forks; the child goes on with the job in its own session while this process waits,
    passes signals on (Ctrl-C, hang-up, terminate), and exits with the child's status. The child dies with
    it."""
    nice = int(os.environ.get(BATCH_NICE_ENV, "19"))
    if nice <= 0:
        return
    if own_session and os.getsid(0) != os.getpid():
        _into_own_session()
    try:
        current = os.getpriority(os.PRIO_PROCESS, 0)
        if current < nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        if hasattr(os, "SCHED_BATCH"):
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (PermissionError, OSError) as exc:
        log.debug("could not lower the priority: %s", exc)
    if os.getsid(0) == os.getpid():
        _lower_session_group(nice)


def _lower_session_group(nice: int) -> None:
    group = Path("/proc/self/autogroup")
    try:
        if int(group.read_text().split("nice")[1]) < nice:
            group.write_text(str(nice))
    except (OSError, ValueError, IndexError) as exc:  # no autogroups here (or in a cgroup): nothing to do
        log.debug("session group left as it is: %s", exc)


def _end_session(_number: int, _frame) -> None:
    """SIGTERM in a batch job's own session (its parent died, or passed it on): end every process of the
    session's group (pool workers, a forkserver), this one last."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.killpg(0, signal.SIGTERM)


def _into_own_session() -> None:
    if threading.active_count() > 1 or not hasattr(os, "setsid"):
        return  # forking a process with threads is unsafe; the job stays where it is
    # Even a process that could call setsid() itself (one that is not its group's leader) forks: in a new
    # session it would escape whoever signals its group (a test runner's kill, `timeout`); this process
    # stays in the group and takes the child with it.
    parent = os.getpid()
    sys.stdout.flush()
    sys.stderr.flush()
    passed_on = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT}
    # held back over the fork: one that comes before this process forwards them waits, and is forwarded
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, passed_on)
    child = os.fork()
    if child == 0:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        os.setsid()
        signal.signal(signal.SIGTERM, _end_session)  # the job's worker processes go with it
        die_with_parent(parent, signal.SIGTERM)
        return

    def forward(number: int, _frame) -> None:  # to the job's whole group, as a terminal signals its job
        try:
            os.killpg(child, number)
        except ProcessLookupError:  # the child has not made its session yet
            os.kill(child, number)

    for sig in passed_on:
        signal.signal(sig, forward)
    signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    _, status = os.waitpid(child, 0)
    code = os.waitstatus_to_exitcode(status)
    os._exit(code if code >= 0 else 128 - code)
