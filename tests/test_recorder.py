"""The real-time recorder (a supervisor, one daemon per device, a writer process) against the rig.

Every test here asserts rates and losses, not only that a session completed; they hold on a busy computer
(run them under `make test-under-load`)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
from mcap.reader import make_reader

from acquisition.recorder.recorder import Recorder
from acquisition.recorder.sessions import recover_session, session_info
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from acquisition.schemas.session_card import readable_parts
from twin.ptyhost import send_control

RIG = {"module": "twin.rig", "extra": ("--robot", "vsl")}
ROOT = Path(__file__).resolve().parents[1]
SAMPLED = {T.SERVO_STATE: "seq", T.PRESSURE: "seq", T.STEPPER: "seq", T.TRACKER: "frame"}
DEVICE = {
    T.SERVO_STATE: "servo_bus",
    T.PRESSURE: "pressure_board",
    T.STEPPER: "stepper_board",
    T.TRACKER: "tracker",
}
SLOT_NUMBERED = {T.SERVO_STATE}  # numbered by poll slot: the numbers go on across a gap
# the servo bus at the description's 250 Hz (1 kHz once, more than a real 1 Mbaud bus behind a 1 ms latency
# timer carries: its wire's ceiling is 588 Hz, and the rig keeps the wire's timing; then 400 Hz, which left
# the host 4 % of each slot and lost samples in every recording; then 300 Hz, which lost samples where a
# hypervisor took a tenth of the CPUs: configs/robots/vsl.yaml)
RATES = {T.SERVO_STATE: 250.0, T.PRESSURE: 250.0, T.STEPPER: 100.0, T.TRACKER: 40.0}


def file_account(parts: list[Path], robot) -> dict[str, dict]:
    """Each sampled stream's account computed from the files alone, with mcap's own reader: messages, rate,
    and samples expected from the sequence numbers; across a gap the events mark (a device that may have
    reset), or where a number does not follow, the time since the last sample at the stream's rate."""
    topics = T.session_topics(robot)
    seen: dict[str, list[tuple[int, int]]] = {topic: [] for topic in SAMPLED}
    gaps: dict[str, list[int]] = {}
    for part in parts:
        with open(part, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(topics=[*SAMPLED, T.EVENTS]):
                if channel.topic == T.EVENTS:
                    event = Event.decode(message.data)
                    if event.kind == EventKind.DEVICE_GAP_START:
                        gaps.setdefault(event.label, []).append(message.log_time)
                    continue
                rows = topics[channel.topic].message.decode(message.data)
                seen[channel.topic].append((message.log_time, int(rows[SAMPLED[channel.topic]][0])))
    out = {}
    for topic, pairs in seen.items():
        t, seq = (np.array(x, dtype=np.int64) for x in zip(*sorted(pairs), strict=True))
        step = (np.diff(seq) % 2**32).astype(np.int64)
        bridged = np.maximum(1, np.rint(np.diff(t) * RATES[topic] / 1e9)).astype(np.int64)
        across_gap = np.zeros(len(step), bool)
        if topic not in SLOT_NUMBERED:
            for g in gaps.get(DEVICE[topic], []):
                across_gap |= (t[:-1] <= g) & (t[1:] > g)
        step = np.where((step >= 2**31) | across_gap, bridged, step)
        duration = (t[-1] - t[0]) / 1e9
        out[topic] = {"messages": len(t), "expected": 1 + int(step.sum()), "rate_hz": (len(t) - 1) / duration,
                      "longest_gap_s": float(np.diff(t).max() / 1e9)}  # fmt: skip
    return out


def _card(directory: Path) -> dict:
    return json.loads((directory / "session.json").read_text())


def _events(directory: Path) -> list[tuple[int, Event]]:
    return [e for part in readable_parts(directory) for e in read_events(part)]


@pytest.mark.slow
def test_a_session_meets_its_rates_loses_nothing_and_its_file_agrees(
    host_factory, tmp_path, vsl, ros2_agrees, real_time
):
    """Servo 250 Hz, pressure 250 Hz, stepper 100 Hz, tracker 40 Hz: every sample expected is received and
    written; the account computed from the file with the mcap reader equals session.json's; the generic
    ROS 2 decoder reads every message as the fast path does. VSLAB_RECORD_S sets the length (default 8 s)."""
    seconds = float(os.environ.get("VSLAB_RECORD_S", "8"))
    with host_factory(**RIG) as ports, Recorder(vsl, ports, tmp_path / "s", "rt") as rec:
        time.sleep(seconds)
    card = _card(tmp_path / "s")
    assert card["status"] == "complete" and rec.write_error is None
    real_time(rec)
    account = file_account(readable_parts(tmp_path / "s"), vsl)
    for topic, rate in RATES.items():
        c, f = card["counters"][topic], account[topic]
        assert c["lost"] == 0 and c["dropped"] == 0 and c["gaps"] == 0, (topic, c)
        assert c["expected"] == c["received"] == c["written"] == f["messages"] == f["expected"], (topic, c, f)
        assert f["rate_hz"] == pytest.approx(rate, rel=0.01), topic
        assert f["messages"] >= rate * (seconds - 1.5), (topic, f)  # all along, after the connections
    # every stream ends when the recording stops: the tracker's polls (2.5 a frame, 9 ms each) fill its
    # slots, and its daemon still hears the stop command at once (it was SIGTERMed 5 s later)
    ends = [card["counters"][topic]["last_ns"] for topic in RATES]
    assert (max(ends) - min(ends)) / 1e9 < 0.5, ends
    (part,) = readable_parts(tmp_path / "s")
    ros2_agrees(part)


@pytest.mark.slow
def test_rate_override_sets_the_servo_poll_rate(host_factory, tmp_path, vsl, real_time):
    """``rates=`` (``vslab record --rate servo_bus=200``) polls the bus at that rate, not the description's
    250 Hz. (How fast the bus can be polled is bench/bus.py's to measure. 500 Hz, asked here while the rig
    answered at once, is now 85 % of the wire's ceiling at 1 Mbaud behind a 1 ms latency timer, and the
    host's own time per read on a busy 2-core machine pushes it past its slot: 200 Hz, below the
    description's rate as the override's point is a rate other than it.)"""
    with host_factory(**RIG) as ports:
        with Recorder(vsl, ports, tmp_path / "s", "slow", rates={"servo_bus": 200}) as rec:
            time.sleep(3.0)
    real_time(rec)
    c = rec.final[T.SERVO_STATE]
    assert c["lost"] == 0 and c["expected"] == c["written"]
    assert file_account(readable_parts(tmp_path / "s"), vsl)[T.SERVO_STATE]["rate_hz"] == pytest.approx(
        200, rel=0.01
    )
    assert json.loads(_card(tmp_path / "s")["rates_hz"])["servo_bus"] == 200


def _plug_pressure_board_back(run_dir: Path, rec: Recorder) -> None:
    """Plug the pressure board in again and record until its stream is back (and half a second more)."""
    send_control(run_dir, {"op": "fault", "device": "pressure_board", "kind": "plug"})
    deadline = time.monotonic() + 10.0  # the Uno resets when the port opens again (~1.4 s boot)
    while not rec.connected(T.PRESSURE) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)


@pytest.mark.slow
def test_an_unplugged_device_is_a_marked_gap_counted_lost_and_the_others_keep_recording(
    host_factory, tmp_path, vsl, real_time
):
    with host_factory(**RIG) as ports:
        run_dir = tmp_path / "run"
        with Recorder(vsl, ports, tmp_path / "s", "gap") as rec:
            time.sleep(1.0)
            send_control(run_dir, {"op": "fault", "device": "pressure_board", "kind": "unplug"})
            time.sleep(1.5)
            _plug_pressure_board_back(run_dir, rec)
    kinds = [(e.kind, e.label) for _, e in _events(tmp_path / "s")]
    real_time(rec)
    assert (EventKind.DEVICE_GAP_START, "pressure_board") in kinds
    assert (EventKind.DEVICE_GAP_END, "pressure_board") in kinds
    account = file_account(readable_parts(tmp_path / "s"), vsl)
    card = _card(tmp_path / "s")["counters"]
    pressure = card[T.PRESSURE]
    assert pressure["gaps"] == 1 and pressure["lost"] > 250  # > 1 s at 250 Hz
    assert pressure["expected"] == pressure["received"] + pressure["lost"] == account[T.PRESSURE]["expected"]
    assert account[T.PRESSURE]["longest_gap_s"] > 1.0
    for topic in (T.SERVO_STATE, T.STEPPER, T.TRACKER):  # the other streams never noticed
        assert card[topic]["lost"] == 0 and card[topic]["gaps"] == 0, topic
        assert account[topic]["expected"] == card[topic]["expected"], topic


@pytest.mark.slow
def test_a_device_absent_when_the_recording_starts_counts_its_wait_as_lost(
    host_factory, tmp_path, vsl, real_time
):
    """A stream that starts in a gap (the device did not answer at first) has no earlier sample to bridge
    from: the time from its first failed attempt to its first sample is counted lost, not left out."""
    with host_factory(**RIG) as ports:
        run_dir = tmp_path / "run"
        send_control(run_dir, {"op": "fault", "device": "pressure_board", "kind": "unplug"})
        with Recorder(vsl, ports, tmp_path / "s", "late") as rec:
            time.sleep(1.5)
            _plug_pressure_board_back(run_dir, rec)
    real_time(rec)
    pressure = _card(tmp_path / "s")["counters"][T.PRESSURE]
    assert pressure["gaps"] == 1 and pressure["lost"] > 1.5 * 250, pressure  # > 1.5 s at 250 Hz
    assert pressure["expected"] == pressure["received"] + pressure["lost"]
    assert _card(tmp_path / "s")["counters"][T.SERVO_STATE]["lost"] == 0


@pytest.mark.slow
def test_corrupted_replies_are_retried_in_place(host_factory, tmp_path, vsl, real_time):
    """A few corrupted Sync Read replies: retried within their slot, no reconnection, no gap."""
    with host_factory(**RIG) as ports, Recorder(vsl, ports, tmp_path / "s", "corrupt") as rec:
        time.sleep(1.0)
        send_control(tmp_path / "run", {"op": "fault", "device": "servo_bus", "kind": "corrupt", "count": 3})
        time.sleep(1.0)
    c = rec.final[T.SERVO_STATE]
    assert c["expected"] == c["received"] + c["lost"]  # the account adds up whatever the host did
    real_time(rec)  # CI lost 158 samples here with seconds of CPU stolen: the budget below is the code's
    assert c["gaps"] == 0 and c["lost"] <= 3, c
    assert not [e for _, e in _events(tmp_path / "s") if e.kind == EventKind.DEVICE_GAP_START]


@pytest.mark.slow
def test_a_killed_daemon_is_restarted_within_a_second_and_only_its_stream_has_a_gap(
    host_factory, tmp_path, vsl, real_time
):
    """The spare daemon takes over: the first sample ≤ 0.5 s after the kill (a daemon started from nothing
    took 0.65–0.9 s to import on this 2-core machine, 1.2 s once in the real-time tier); a new spare waits
    for the next death, and takes over the same way when the new daemon is killed too. (The boards' daemons
    come back as fast, but an Uno resets when its port opens again: 1.4 s of boot, counted lost.)"""
    kills = []
    with host_factory(**RIG) as ports, Recorder(vsl, ports, tmp_path / "s", "kill") as rec:
        time.sleep(1.5)
        for _ in range(2):
            assert rec.spare_ready(timeout_s=10.0)  # started up (imports: 0.5–0.9 s, more under load)
            pid, spare = rec._children["servo_bus"].proc.pid, rec._spare.proc.pid
            kills.append(time.monotonic_ns())
            os.kill(pid, signal.SIGKILL)
            time.sleep(2.0)
            assert rec._children["servo_bus"].proc.pid == spare  # the spare became the servo bus's daemon
            assert rec._spare.proc.pid not in (pid, spare)  # and a new one waits
        last_spare = rec._spare.proc
    assert rec._spare is None and last_spare.returncode == 0  # it ended with the recording, told nothing
    real_time(rec)
    assert rec.restarts == {"servo_bus": 2}
    events = _events(tmp_path / "s")
    starts = [(t, e) for t, e in events if e.kind == EventKind.DEVICE_GAP_START and e.label == "servo_bus"]
    ends = [(t, e) for t, e in events if e.kind == EventKind.DEVICE_GAP_END and e.label == "servo_bus"]
    assert len(starts) == 2 and all("SIGKILL" in e.text for _, e in starts) and len(ends) == 2
    assert all(e.value < 0.5 for _, e in ends), "back within half a second"
    data = read_fixed_topics(readable_parts(tmp_path / "s")[0])
    servo_t = data[T.SERVO_STATE].log_time
    offset = time.time_ns() - time.monotonic_ns()
    for killed in kills:
        after = servo_t[servo_t > killed + offset]
        assert len(after) and (after[0] - (killed + offset)) / 1e9 < 0.5
    c = rec.final[T.SERVO_STATE]
    assert c["gaps"] == 2 and 0 < c["lost"] < 2 * 0.5 * RATES[T.SERVO_STATE], c
    assert c["expected"] == c["received"] + c["lost"]
    account = file_account(readable_parts(tmp_path / "s"), vsl)
    assert account[T.SERVO_STATE]["expected"] == c["expected"]
    # no other stream loses a sample, or waits longer than three periods or 40 ms (a 2-core machine is busy
    # while the new daemon connects; measured up to 25 ms)
    for topic in (T.PRESSURE, T.STEPPER, T.TRACKER):
        assert account[topic]["longest_gap_s"] <= max(3.0 / RATES[topic], 0.040), topic
        assert rec.final[topic]["lost"] == 0, topic


@pytest.mark.slow
def test_a_killed_writer_is_restarted_and_loses_at_most_a_fifth_of_a_second(
    host_factory, tmp_path, vsl, real_time
):
    with host_factory(**RIG) as ports, Recorder(vsl, ports, tmp_path / "s", "writer") as rec:
        time.sleep(1.5)
        os.kill(rec._children["writer"].proc.pid, signal.SIGKILL)
        time.sleep(2.0)
    assert rec.restarts == {"writer": 1} and rec.write_error is None
    info = session_info(tmp_path / "s")
    assert info.status == "complete" and len(info.parts) == 2 and len(info.torn) == 1  # the killed part
    (report,) = recover_session(tmp_path / "s")
    assert report.torn and report.messages > 0
    accounts = file_account(readable_parts(tmp_path / "s"), vsl)
    for topic, rate in RATES.items():
        c = rec.final[topic]
        assert c["written"] + c["dropped"] == c["received"], (topic, c)
        assert c["dropped"] <= 0.2 * rate + 1, (topic, c)  # what the killed writer had not made durable
        assert accounts[topic]["messages"] == c["written"], topic
    real_time(rec)  # the devices' samples were all taken (the writer's death costs the daemons nothing)
    for topic, rate in RATES.items():
        assert rec.final[topic]["lost"] == 0, (topic, rec.final[topic])
        assert accounts[topic]["longest_gap_s"] <= 0.2 + 2 / rate, topic


def _record_cli(lab: Path, session: str, *args: str) -> subprocess.Popen:
    cli = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "--quiet"]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    return subprocess.Popen([*cli, "record", "--session", session, *args], cwd=ROOT, **quiet)


@pytest.mark.slow
def test_a_killed_supervisor_leaves_no_process_and_a_whole_file(tmp_path, vsl):
    """`vslab record --rig` killed with SIGKILL: every daemon, the writer and the rig end by themselves
    within a second; the writer closes the session (whole, not torn) with ≤ 0.2 s lost per stream."""
    lab = tmp_path / "lab"
    proc = _record_cli(lab, "killed", "--rig")
    session = lab / "sessions" / "killed"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (session / "session.json").exists():
        time.sleep(0.1)
    time.sleep(3.0)
    children = psutil.Process(proc.pid).children(recursive=True)
    assert len(children) >= 7  # the rig, four daemons, the writer, the spare daemon
    assert any("--spare" in p.cmdline() for p in children)
    kill_ns = time.time_ns()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _, alive = psutil.wait_procs(children, timeout=3.0)
    assert not alive, f"orphans: {[(p.pid, p.cmdline()) for p in alive]}"
    info = session_info(session)
    assert info.status == "complete" and not info.torn
    kinds = [e for _, e in _events(session) if e.kind == EventKind.SESSION_END]
    assert kinds and "supervisor died" in kinds[-1].text
    data = read_fixed_topics(readable_parts(session)[0])
    for topic in RATES:
        t = data[topic].log_time
        assert kill_ns - t[-1] <= 0.2e9, f"{topic}: lost {(kill_ns - t[-1]) / 1e9:.2f} s"
    assert not list(Path("/dev/shm").glob(f"vslab-{proc.pid}-*"))


@pytest.mark.slow
def test_a_failing_live_view_never_stops_the_recording(host_factory, tmp_path, vsl, caplog, real_time):
    class Broken:
        def publish(self, *args):
            raise OSError("viewer gone")

    with host_factory(**RIG) as ports, Recorder(vsl, ports, tmp_path / "s", "broken", live=Broken()) as rec:
        rec.event(Event(EventKind.NOTE, text="still recorded"))
        time.sleep(0.5)
    assert rec.write_error is None and rec.live_errors > 1
    assert sum("live view failed" in r.message for r in caplog.records) == 1  # logged once
    assert session_info(tmp_path / "s").status == "complete"
    real_time(rec)
    assert rec.final[T.SERVO_STATE]["lost"] == 0


def test_a_device_short_of_time_is_named_where_its_polls_are_its_samples(tmp_path, vsl):
    """After a recording, the servo bus (a sample a poll) is named once it fell more than half of MAX_LAG_S
    behind (past it, missed polls are skipped and counted lost); the tracker, polled faster than its frames
    and always some way behind, is not."""
    ports = {name: "/dev/null" for name in vsl.devices}
    rec = Recorder(vsl, ports, tmp_path / "s", "late")  # not started: the account set as a stopped one's
    rec.behind_ms = {"servo_bus": 53.2, "tracker": 61.0, "pressure_board": 0.0, "stepper_board": 0.0}
    assert rec.short_of_time() == {"servo_bus": 53.2}
    rec.behind_ms["servo_bus"] = 13.0  # the 250 Hz it is described at: at most 13-31 ms
    assert rec.short_of_time() == {}
