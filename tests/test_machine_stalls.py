"""The real-time tests' witness of a stopped machine (``tests/machine_stalls.py``): the stall watch sees a
stop of its process as the stop of a descheduled VM looks to it, and the check skips a recording so
stopped, saying why."""

from __future__ import annotations

import os
import signal
import time

import pytest
from machine_stalls import RealTimeCheck, StallWatch


def _stopped(watch: StallWatch, seconds: float) -> None:
    """The watch's process stopped for ``seconds``, as a VM the hypervisor deschedules stops every process."""
    os.kill(watch._process.pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(watch._process.pid, signal.SIGCONT)


def test_the_watch_keeps_the_longest_it_was_not_run_and_starts_afresh():
    watch = StallWatch()
    try:
        _stopped(watch, 0.2)
        assert watch.longest_ms() >= 150
        watch.reset()
        time.sleep(0.05)
        assert watch.longest_ms() < 150  # the stop was before the reset
    finally:
        watch.close()
    assert watch._process.returncode == 0  # it ends at the end of its input


def test_a_recording_the_machine_stopped_is_skipped_with_why():
    check = RealTimeCheck()
    try:
        if not check.stalls.real_time:
            pytest.skip("this machine does not allow real-time priority: the watch is not asked")
        check()  # nothing stopped it yet (a VM stopped 50 ms meanwhile would skip here, saying so)
        _stopped(check.stalls.watches[-1], 0.2)  # one CPU stopped, the others running on
        with pytest.raises(pytest.skip.Exception, match=r"CPU \d+ ran nothing for \d+ ms at once"):
            check()
        check.recording()  # a recording that starts after the stop
        check()
    finally:
        check.close()


def test_a_recording_during_which_the_hypervisor_took_a_tenth_of_the_cpus_is_skipped(monkeypatch):
    """Steal in slices too short for a watch to call a stop is judged by its share of the CPUs: below
    STEAL_SHARE the check passes, at it the recording is skipped, saying how much was taken."""
    import machine_stalls

    stolen = [100.0]  # s since boot, as /proc/stat counts it
    monkeypatch.setattr(machine_stalls, "cpu_stolen_s", lambda: stolen[0])
    check = RealTimeCheck()
    try:
        if not check.stalls.real_time:
            pytest.skip("this machine does not allow real-time priority: the steal's 50 ms judges there")
        time.sleep(0.5)
        cpus = len(check.stalls.watches)
        stolen[0] += 0.5 * machine_stalls.STEAL_SHARE * cpus * 0.5  # half the share in 0.5 s
        check()
        stolen[0] += 4 * machine_stalls.STEAL_SHARE * cpus * 0.5
        with pytest.raises(pytest.skip.Exception, match=r"the hypervisor took \d+% of this machine's CPUs"):
            check()
    finally:
        check.close()
