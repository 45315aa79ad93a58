"""Whether the machine itself stopped during a real-time recording, so the tests that judge one can tell a
stall of the computer from a fault of the code.

Two witnesses. The hypervisor's own count of the CPU it took (``steal`` in /proc/stat, :func:`cpu_stolen_s`,
sampled over time by :class:`StealWatch`). And a stall watch (:class:`StallWatch`): a process at real-time
priority (SCHED_FIFO at the highest priority: above the device daemons', ``acquisition.processes``; at the
lowest, a daemon's start kept it waiting 128 ms in half the real-time tests) that asks to be woken every
millisecond and keeps the longest it waited. Busy cores do not delay it (it runs before every other process
the moment it is due: with both cores busy, ``bench/load.py``, its longest wait in each of 20 seconds was
0.0–1.5 ms), so a wait of tens of milliseconds means no CPU ran at all — the VM was descheduled or throttled,
which steal counts in 10 ms ticks or, on some hosts, not at all (a CI run lost 0.1–0.2 s of samples in three
recordings whose steal came to under 50 ms, in an hour when a plain 3 s recording counted 3 s of it). Where
real-time priority is not allowed the watch runs as an ordinary process and is not asked: a busy machine would
delay it too.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from acquisition.recorder.daemon import MAX_LAG_S


def cpu_stolen_s() -> float:
    """Seconds of this machine's CPU the hypervisor has taken since boot (``steal`` in /proc/stat; 0 where
    there is none to read)."""
    try:
        with open("/proc/stat") as f:
            return int(f.readline().split()[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


class StealWatch:
    """What the hypervisor takes of the CPUs (:func:`cpu_stolen_s`), sampled every ``every_s`` in a thread
    from ``start()`` to ``stop()``: ``total_ms`` in all, ``burst_ms(window_s)`` the most within any window of
    that length (one stall, which a real-time loop meets, not the same time spread thin)."""

    def __init__(self, every_s: float = 0.02) -> None:
        self.every_s = every_s
        self._samples: list[tuple[float, float]] = []
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def start(self) -> StealWatch:
        self._thread.start()
        return self

    def stop(self) -> StealWatch:
        self._stopped.set()
        self._thread.join()
        return self

    def _sample(self) -> None:
        while True:
            self._samples.append((time.monotonic(), cpu_stolen_s()))
            if self._stopped.wait(self.every_s):
                self._samples.append((time.monotonic(), cpu_stolen_s()))
                return

    @property
    def total_ms(self) -> float:
        return (self._samples[-1][1] - self._samples[0][1]) * 1e3

    def burst_ms(self, window_s: float) -> float:
        t, stolen = np.array(self._samples).T
        end = np.searchsorted(t, t + window_s, side="right") - 1
        return float((stolen[end] - stolen).max() * 1e3)


# The watch's own process: woken every millisecond by select's timeout, it keeps the longest it went without
# running; on stdin, "r" starts afresh and "q" writes that longest wait (ms) beyond the millisecond asked.
_WATCH = r"""
import os, select, sys, time
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(os.sched_get_priority_max(os.SCHED_FIFO)))
    os.write(1, b"fifo\n")
except (AttributeError, OSError):
    os.write(1, b"ordinary\n")
worst, last = 0.0, time.monotonic()
while True:
    ready = select.select([0], [], [], 0.001)[0]
    now = time.monotonic()
    worst, last = max(worst, now - last), now
    if ready:
        command = os.read(0, 1)
        if not command:
            break
        if command == b"r":
            worst = 0.0
        elif command == b"q":
            os.write(1, b"%.1f\n" % max((worst - 0.001) * 1e3, 0.0))
        last = time.monotonic()
"""


class StallWatch:
    """The longest the watch waited past its millisecond since ``reset()`` (or the start): ``longest_ms()``.
    Where it runs at real-time priority (``real_time``) that is the longest the machine ran no process at
    all; where it could not take that priority, its waits count the load too."""

    def __init__(self) -> None:
        self._process = subprocess.Popen([sys.executable, "-c", _WATCH], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE)  # fmt: skip
        self.real_time = self._process.stdout.readline().strip() == b"fifo"

    def reset(self) -> None:
        self._send(b"r")

    def longest_ms(self) -> float:
        self._send(b"q")
        return float(self._process.stdout.readline())

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.stdin.close()  # the watch ends at the end of its input
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process.stdout.close()

    def _send(self, command: bytes) -> None:
        self._process.stdin.write(command)
        self._process.stdin.flush()


class RealTimeCheck:
    """Skips the test that calls it when the machine stopped for ``MAX_LAG_S`` or more during the recording:
    the hypervisor's steal came to that much, or the stall watch waited that long at once."""

    def __init__(self) -> None:
        self.stalls = StallWatch()
        self.recording()

    def recording(self) -> None:
        """The recording starts now: what was stolen, or stalled, before it is not counted."""
        self.start_s = cpu_stolen_s()
        self.stalls.reset()

    def __call__(self) -> None:
        stolen = cpu_stolen_s() - self.start_s
        if stolen >= MAX_LAG_S:
            pytest.skip(f"the hypervisor took {stolen * 1e3:.0f} ms of this machine's CPU during the "
                        "recording (steal in /proc/stat)")  # fmt: skip
        longest = self.stalls.longest_ms()
        if self.stalls.real_time and longest >= MAX_LAG_S * 1e3:
            pytest.skip(f"the machine ran nothing for {longest:.0f} ms at once during the recording (a "
                        "process at real-time priority waited that long to be woken)")  # fmt: skip

    def close(self) -> None:
        self.stalls.close()
