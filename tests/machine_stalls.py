"""Whether the machine itself stopped during a real-time recording, so the tests that judge one can tell a
stall of the computer from a fault of the code.

The witness is a stall watch on each CPU (:class:`StallWatch`, :class:`StallWatches`): a process held on that
CPU (``sched_setaffinity``) at real-time priority (SCHED_FIFO at the highest priority: above the device
daemons', ``acquisition.processes``) that asks to be woken every 5 ms and keeps the longest it waited.
Busy cores do not delay it (it runs before every other process the moment it is due: with both cores busy,
``bench/load.py``, its longest wait in each of 20 seconds was 0.0–1.5 ms), so a wait of tens of milliseconds
means that CPU ran nothing at all: the hypervisor stopped it. One a CPU, because a hypervisor may stop one
virtual CPU while the other runs on; a watch free to move is woken on the CPU that runs and sees nothing,
while a daemon on the stopped one falls behind. A check skips a recording when a CPU stopped for
``STALL_S`` at once: ``MAX_LAG_S`` less what the code itself may take of it (``OWN_S``).

The hypervisor's own count (``steal`` in /proc/stat, :func:`cpu_stolen_s`, sampled by :class:`StealWatch`) is
reported, not judged, where the watches run at real-time priority. On this project's machines it counts the
cost of waking a virtual CPU as well as a stop: the two watches alone add 6–9 ms of steal a second, a whole
recording 20–450 ms while no CPU stopped for more than 7 ms. Judged by it (skipped at 50 ms), half the
real-time tests were skipped in every run, and among them the recordings that lost samples through a fault
of the code (the servo bus polled at 96 % of what its reads allowed: ``configs/robots/vsl.yaml``). It is
judged by its share instead: a hypervisor can take a large part of each CPU in slices too short for a watch
to call a stop (CI's host took 11–13 % so, and the servo bus fell 60–70 ms behind), and a recording during
which the steal came to ``STEAL_SHARE`` of the CPUs (10 %, where the recorder is measured to hold its
rates; this project's machines, wake-ups and all: 0.1–4.5 %) is skipped with that said. Where real-time
priority is not allowed the watches wait on the load too, and only the steal is asked.

Each check writes what it saw into the test's report (shown where the test fails): the steal, each CPU's
longest stop, and, given the recorder, how far each daemon fell behind its schedule and the scheduling each
got — a failure says whether the machine or the code lost the samples.
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

    @property
    def share(self) -> float:
        """What was taken, as a share of the CPUs this process may use over the time watched."""
        seconds = max(self._samples[-1][0] - self._samples[0][0], 1e-3)
        return self.total_ms / 1e3 / (len(os.sched_getaffinity(0)) * seconds)

    def burst_ms(self, window_s: float) -> float:
        t, stolen = np.array(self._samples).T
        end = np.searchsorted(t, t + window_s, side="right") - 1
        return float((stolen[end] - stolen).max() * 1e3)


# The watch's own process: woken every WATCH_PERIOD_S by select's timeout, it keeps the longest it went
# without running; on stdin, "r" starts afresh and "q" writes that longest wait (ms) beyond the period asked.
# How often a watch asks to be woken. Every 1 ms, the watches themselves made the CAN drives miss SYNC answers
# (4 of 960 cycles beside them, none of 960 without; at 5 ms none of 960); a stop of STALL_S is 8 periods.
WATCH_PERIOD_S = 0.005
_WATCH = r"""
import os, select, sys, time
PERIOD_S = float(os.environ["VSLAB_WATCH_PERIOD_S"])
if len(sys.argv) > 1:
    os.sched_setaffinity(0, {int(sys.argv[1])})
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(os.sched_get_priority_max(os.SCHED_FIFO)))
    os.write(1, b"fifo\n")
except (AttributeError, OSError):
    os.write(1, b"ordinary\n")
worst, last = 0.0, time.monotonic()
while True:
    ready = select.select([0], [], [], PERIOD_S)[0]
    now = time.monotonic()
    worst, last = max(worst, now - last), now
    if ready:
        command = os.read(0, 1)
        if not command:
            break
        if command == b"r":
            worst = 0.0
        elif command == b"q":
            os.write(1, b"%.1f\n" % max((worst - PERIOD_S) * 1e3, 0.0))
        last = time.monotonic()
"""


def _watch_env() -> dict[str, str]:
    return {**os.environ, "VSLAB_WATCH_PERIOD_S": str(WATCH_PERIOD_S)}


class StallWatch:
    """The longest the watch waited past its period (``WATCH_PERIOD_S``) since ``reset()`` (or the start):
    ``longest_ms()``. Where it runs at real-time priority (``real_time``) that is the longest the machine ran
    no process at all; where it could not take that priority, its waits count the load too."""

    def __init__(self, cpu: int | None = None) -> None:
        self.cpu = cpu  # the CPU it is held on (None: wherever the scheduler puts it)
        where = [] if cpu is None else [str(cpu)]
        self._process = subprocess.Popen([sys.executable, "-c", _WATCH, *where], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, env=_watch_env())  # fmt: skip
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


class StallWatches:
    """A :class:`StallWatch` held on each CPU this process may use."""

    def __init__(self) -> None:
        self.watches = [StallWatch(cpu) for cpu in sorted(os.sched_getaffinity(0))]

    @property
    def real_time(self) -> bool:
        """Whether they run at real-time priority (else a busy machine delays them too)."""
        return all(watch.real_time for watch in self.watches)

    def reset(self) -> None:
        for watch in self.watches:
            watch.reset()

    def longest_ms(self) -> dict[int, float]:
        """Each CPU's longest stop since the reset (ms)."""
        return {watch.cpu: watch.longest_ms() for watch in self.watches}

    def close(self) -> None:
        for watch in self.watches:
            watch.close()


OWN_S = 0.010  # of MAX_LAG_S, what a daemon itself may take: a poll period (4 ms at 250 Hz) and an answer
STALL_S = MAX_LAG_S - OWN_S  # a machine stopped this long at once leaves the code less than OWN_S
# The share of the CPUs a hypervisor may take while a recording must still hold its rates: the recorder was
# measured holding them with this much of each CPU taken in 3 ms slices (`bench/load.py --steal 0.1`, both
# cores also busy), while the steal count of this project's machines, wake-ups and all, came to 0.1–4.5 % a
# recording. CI's host once took 11–13 % in slices (no CPU stopped for more than 7 ms) and the servo bus fell
# 60–70 ms behind: a machine that is not whole is said so, not judged.
STEAL_SHARE = 0.10


class RealTimeCheck:
    """Skips the test that calls it when the machine stopped during the recording: a CPU's stall watch
    waited ``STALL_S`` at once (or, where the watches cannot run at real-time priority, the hypervisor's
    steal came to ``MAX_LAG_S``), or the hypervisor took ``STEAL_SHARE`` of the CPUs. What it saw goes into
    the test's report either way (``node``: the test's item), with the recorder's daemons where given."""

    def __init__(self, node: pytest.Item | None = None) -> None:
        self.node = node
        self.stalls = StallWatches()
        self.steal: StealWatch | None = None
        self.recording()

    def recording(self) -> None:
        """The recording starts now: what was stolen, or stalled, before it is not counted."""
        self.start_s = cpu_stolen_s()
        self.start_wall_s = time.monotonic()
        self.stalls.reset()
        if self.steal is not None:
            self.steal.stop()
        self.steal = StealWatch().start()

    def __call__(self, recorder=None) -> None:
        stolen = cpu_stolen_s() - self.start_s
        share = stolen / (len(self.stalls.watches) * max(time.monotonic() - self.start_wall_s, 1e-3))
        longest = self.stalls.longest_ms()
        self._report(stolen, share, longest, recorder)
        cpu, worst = max(longest.items(), key=lambda kv: kv[1])
        if share >= STEAL_SHARE:
            pytest.skip(f"the hypervisor took {share:.0%} of this machine's CPUs during the recording (steal "
                        f"in /proc/stat; the rates are held with {STEAL_SHARE:.0%} taken)")  # fmt: skip
        if not self.stalls.real_time:  # the watches wait on the load too: only the steal tells
            if stolen >= MAX_LAG_S:
                pytest.skip(f"the hypervisor took {stolen * 1e3:.0f} ms of this machine's CPU during the "
                            "recording (steal in /proc/stat)")  # fmt: skip
        elif worst >= STALL_S * 1e3:
            pytest.skip(f"CPU {cpu} ran nothing for {worst:.0f} ms at once during the recording (a process "
                        "held there at real-time priority waited that long to be woken)")  # fmt: skip

    def _report(self, stolen_s: float, share: float, longest_ms: dict, recorder) -> None:
        """What the machine did during the recording, into the test's report (shown where it fails)."""
        self.steal.stop()
        stops = ", ".join(f"cpu{c} {ms:.1f}" for c, ms in longest_ms.items())
        burst = self.steal.burst_ms(0.1)
        lines = [f"steal: {stolen_s * 1e3:.0f} ms in all ({share:.1%} of the CPUs), {burst:.0f} ms at most "
                 "within 0.1 s",
                 f"longest stop of each CPU (ms): {stops}"
                 + ("" if self.stalls.real_time else " (ordinary priority: load counts too)")]  # fmt: skip
        if recorder is not None:
            lines.append("the most each daemon fell behind its schedule (ms): "
                         + ", ".join(f"{n} {ms:.1f}" for n, ms in recorder.behind_ms.items()))  # fmt: skip
            lines.append("scheduling: " + ", ".join(f"{n} {p}" for n, p in recorder.scheduling.items()))
        if self.node is not None:
            self.node.add_report_section("call", "machine during the recording", "\n".join(lines))
        self.seen = lines

    def close(self) -> None:
        if self.steal is not None:
            self.steal.stop()
        self.stalls.close()
