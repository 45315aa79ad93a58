"""What a process of a recording does about its parent and the scheduler.

- ``die_with_parent``: a daemon, the writer and the rig end when the process that started them dies, even by
  SIGKILL (Linux ``PR_SET_PDEATHSIG``, checked against the parent's pid to close the race at start-up; a
  caller also polls :func:`parent_alive` where the signal is not available).
- ``elevate``: real-time work asks for a real-time scheduling class where the OS allows it (``SCHED_FIFO``,
  else a negative nice value) and says what it got; without the privilege it runs as it is.
- ``lower_priority``: batch work (training, simulation, dataset builds) yields the CPU to everything else.

On a lab PC, grant the recording user real-time priority once (as root), then log in again::

    # /etc/security/limits.d/99-vslab.conf
    @vslab  -  rtprio  40
    @vslab  -  nice    -10
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
RT_PRIORITY = 30  # SCHED_FIFO priority of device daemons (below the kernel's own threads at 50)
ELEVATE_ENV = "VSLAB_RT_PRIORITY"  # "0" turns elevation off (e.g. to show the targets hold without it)
BATCH_NICE_ENV = "VSLAB_BATCH_NICE"  # the nice value of batch work (default 10; 0 leaves it as it is)


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


def elevate(fifo_priority: int = RT_PRIORITY, nice: int = -10) -> str:
    """Ask for SCHED_FIFO at ``fifo_priority``, else ``nice``; returns what this process runs at."""
    if os.environ.get(ELEVATE_ENV, "1") == "0":
        return "normal (elevation off)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
        return f"SCHED_FIFO {fifo_priority}"
    except (PermissionError, OSError, AttributeError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
        return f"nice {nice}"
    except (PermissionError, OSError):
        return "normal (no privilege to raise it)"


def relinquish() -> None:
    """Back to the ordinary scheduling (a daemon that has stopped acquiring: its teardown must not hold up
    the daemons still reading)."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        if os.getpriority(os.PRIO_PROCESS, 0) < 0:
            os.setpriority(os.PRIO_PROCESS, 0, 0)
    except (PermissionError, OSError, AttributeError):
        pass


def lower_priority() -> None:
    """Batch work: let acquisition and people's programs go first (this process and its children; a nice
    value cannot be raised back without privilege, so only processes that do nothing else call this)."""
    nice = int(os.environ.get(BATCH_NICE_ENV, "10"))
    if nice <= 0:
        return
    try:
        current = os.getpriority(os.PRIO_PROCESS, 0)
        if current < nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        if hasattr(os, "SCHED_BATCH"):
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (PermissionError, OSError) as exc:
        log.debug("could not lower the priority: %s", exc)
