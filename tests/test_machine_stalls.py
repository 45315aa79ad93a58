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
