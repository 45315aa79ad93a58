"""The recorder under faults: a disk that fills while recording, a read-only lab, options that cannot apply,
and each recorder module importable on its own.

A full disk must cost only what could not be written: every part on disk stays readable (or recoverable),
no empty part is left, ``session.json`` says the session failed and why, and every sample the devices gave
is in the account (written or dropped), never missing from it. The small and the read-only file systems are
tmpfs mounts (root only: the tests skip, saying so, where one cannot be made).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from acquisition.recorder.recover import recover
from acquisition.recorder.writer import SessionWriter, WriteFailed
from acquisition.schemas import topics as T
from acquisition.schemas.events import EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from acquisition.schemas.mcap_reader import read_summary
from models.robot import load_robot

ROOT = Path(__file__).resolve().parents[1]
RECORDER_MODULES = sorted(
    p.stem for p in (ROOT / "acquisition" / "recorder").glob("*.py") if p.stem != "__init__"
)


@pytest.fixture
def mount(tmp_path):
    """``mount(size, read_only)``: a fresh tmpfs of ``size`` under ``tmp_path`` (unmounted afterwards)."""
    mounted: list[Path] = []

    def make(size: str, read_only: bool = False) -> Path:
        where = tmp_path / f"fs{len(mounted)}"
        where.mkdir()
        options = f"size={size}" + (",ro" if read_only else "")
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
                              capture_output=True, text=True)  # fmt: skip
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN): {done.stderr.strip()}")
        mounted.append(where)
        return where

    yield make
    for where in mounted:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def _cli(lab: Path, *args: str, timeout_s: float = 180.0) -> subprocess.CompletedProcess:
    """`vslab --lab LAB ARGS` of this tree, in a process of its own (as a user runs it)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "vslab.cli", "--quiet", "--lab", str(lab), *args], env=env,
                          capture_output=True, text=True, timeout=timeout_s)  # fmt: skip


def _messages(part: Path) -> Counter:
    """Messages per topic, read by the mcap package's reader (through the summary and its indexes)."""
    with part.open("rb") as f:
        return Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())


def _readable(part: Path, scratch: Path) -> Path:
    """``part`` itself when it is whole; else its recovered copy (in ``scratch``: the disk is full)."""
    with part.open("rb") as f:
        if read_summary(f) is not None:
            return part
    return recover(part, scratch / part.name.replace(".mcap", ".recovered.mcap")).output


# --------------------------------------------------------------------------------------- imports
@pytest.mark.slow
@pytest.mark.parametrize("module", RECORDER_MODULES)
def test_each_recorder_module_imports_alone(module):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", f"import acquisition.recorder.{module}"], cwd=ROOT, env=env,
                          capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1:]


# ------------------------------------------------------------------------------------- full disk
@pytest.mark.parametrize("threads", [False, True], ids=["compressed-here", "compressed-in-threads"])
def test_a_session_writer_on_a_full_disk_ends_the_session_readable(mount, threads):
    """The writer itself: writes until the disk is full, then one WriteFailed; what was flushed is all in
    the part, which is whole (summary) and ends with an event saying why; the card says failed. Also when
    its chunks compress in threads (the simulated runner's writers)."""
    from concurrent.futures import ThreadPoolExecutor

    directory = mount("256k") / "s"
    robot = load_robot("vsl")
    message = T.session_topics(robot)[T.SERVO_STATE].message
    rng = np.random.default_rng(1)
    flushed, t = 0, 0
    pool = ThreadPoolExecutor(2) if threads else None
    writer = SessionWriter(directory, robot, "s", flush_s=float("inf"), standard_topics=False,
                           chunk_size=16_384, compress_in=pool)  # fmt: skip
    writer.open()
    with pytest.raises(WriteFailed, match="No space left"):
        for k in range(10_000):
            rows = message.empty(200)
            rows.view(np.uint8)[:] = rng.integers(0, 256, rows.nbytes, dtype=np.uint8)  # incompressible
            writer.write(T.SERVO_STATE, np.arange(t, t + 200) * 1_000_000, rows)
            t += 200
            if k % 4 == 3:  # chunks closed (and compressing) between flushes
                writer.flush()
                flushed = t
    with pytest.raises(WriteFailed):  # nothing more is written once it failed
        writer.write(T.SERVO_STATE, np.array([t * 1_000_000]), message.empty(1))
    writer.close()
    if pool is not None:
        pool.shutdown()
    assert flushed > 0, "the disk filled before anything was written: make the file system bigger"
    assert [p.name for p in directory.glob("*.mcap")] == ["s_000.mcap"]
    part = directory / "s_000.mcap"
    assert _messages(part)[T.SERVO_STATE] == flushed  # what was flushed before the disk filled, all of it
    assert len(read_fixed_topics(part, [T.SERVO_STATE])[T.SERVO_STATE]) == flushed
    (_, last), *_ = [e for e in reversed(read_events(part))]
    assert last.kind == EventKind.NOTE and "No space left" in last.text
    card = json.loads((directory / "session.json").read_text())
    assert card["status"] == "failed" and "No space left on device" in card["failure"]


@pytest.mark.slow
def test_a_recording_that_fills_the_disk_fails_in_words_and_keeps_what_it_wrote(mount, tmp_path):
    """`vslab record --rig` on a small file system: one error line, exit 2; every part readable (or
    recovered), no empty part; the samples written before the disk filled all in the parts; session.json
    failed with the reason; every sample received is written or dropped."""
    lab = mount("768k")
    done = _cli(lab, "record", "--rig", "--duration", "60", "--session", "full")
    assert done.returncode == 2, done.stdout + done.stderr
    errors = [line for line in done.stdout.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "No space left on device" in errors[0], done.stdout
    assert "Traceback" not in done.stdout + done.stderr
    session = lab / "sessions" / "full"
    parts = sorted(session.glob("full_*.mcap"))
    assert parts and all(p.stat().st_size > 0 for p in parts), [(p.name, p.stat().st_size) for p in parts]
    card = json.loads((session / "session.json").read_text())
    assert card["status"] == "failed" and "No space left on device" in card["failure"]
    assert "No space left on device" in (session / "logs" / "writer.log").read_text()
    in_parts: Counter = Counter()
    for part in parts:
        readable = _readable(part, tmp_path)
        in_parts += _messages(readable)
        for topic, data in read_fixed_topics(readable).items():
            assert len(data) == _messages(readable)[topic]
    for topic, c in card["counters"].items():
        assert c["received"] == c["written"] + c["dropped"], (topic, c)  # the account adds up
        assert c["expected"] == c["received"] + c["lost"], (topic, c)
        assert in_parts[topic] == c["written"], (topic, c)  # written: in the file, all of it
    assert card["counters"][T.SERVO_STATE]["written"] > 0


# ------------------------------------------------------------------------------- read-only, --ports
def test_record_on_a_rig_in_a_read_only_lab_is_one_error_line(mount):
    lab = mount("64k", read_only=True)
    done = _cli(lab, "record", "--rig", "--duration", "1", "--session", "ro")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    errors = [line for line in done.stdout.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(lab / "rig" / "ro") in errors[0], done.stdout
    assert not [pid for pid in os.listdir("/proc") if pid.isdigit() and _runs_in(pid, lab)]  # nothing left


def _runs_in(pid: str, lab: Path) -> bool:
    try:
        return str(lab) in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.parametrize("command", [["record", "--duration", "1"], ["run", "popup_deploy"]])
def test_ports_with_rig_is_refused_not_ignored(tmp_path, command):
    ports = tmp_path / "ports.json"
    ports.write_text(json.dumps({"servo_bus": "/dev/null"}))
    lab = tmp_path / "lab"
    done = _cli(lab, *command, "--rig", "--ports", str(ports), "--session", "p")
    assert done.returncode == 2, done.stdout + done.stderr
    errors = [line for line in done.stdout.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "--ports" in errors[0] and "--rig" in errors[0], done.stdout
    assert not (lab / "sessions" / "p").exists() and not (lab / "rig" / "p").exists()


def test_sessions_recover_takes_a_torn_part_before_empty_trailing_ones(tmp_path):
    """What a writer that died on a full disk used to leave: a torn part, then empty parts it opened. The
    empty trailing parts are no part of the session: `sessions recover` mends the torn one; `info` reads it
    all."""
    session = tmp_path / "lab" / "sessions" / "s"
    robot = load_robot("vsl")
    message = T.session_topics(robot)[T.SERVO_STATE].message
    with SessionWriter(session, robot, "s", standard_topics=False) as writer:
        for k in range(20):
            writer.write(T.SERVO_STATE, np.arange(k * 100, (k + 1) * 100) * 1_000_000, message.empty(100))
            writer.flush()
    part = session / "s_000.mcap"
    part.write_bytes(part.read_bytes()[: part.stat().st_size * 2 // 3])  # torn in its last chunks
    for k in (1, 2, 3):
        (session / f"s_{k:03d}.mcap").write_bytes(b"")
    done = _cli(tmp_path / "lab", "sessions", "recover", "s")
    assert done.returncode == 0 and "Traceback" not in done.stdout + done.stderr, done.stdout + done.stderr
    recovered = session / "s_000.recovered.mcap"
    assert 0 < _messages(recovered)[T.SERVO_STATE] < 2000
    done = _cli(tmp_path / "lab", "sessions", "info", "s")
    assert done.returncode == 0 and "error:" not in done.stdout, done.stdout + done.stderr
