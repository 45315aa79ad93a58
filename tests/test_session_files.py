"""Session files: what SessionWriter writes is standard MCAP that mcap's own reader, the ros2 decoder and the
chunk-level fast reader agree on; rotation splits a session into complete parts; torn parts recover."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from acquisition.recorder.recover import RECOVERED_SUFFIX, recover
from acquisition.recorder.writer import (
    COUNTERS_METADATA,
    SESSION_CARD,
    SESSION_METADATA,
    RotationPolicy,
    SessionWriter,
)
from acquisition.schemas import Event, EventKind, FixedMessage
from acquisition.schemas.cdr import PRIMITIVES, SchemaError
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.scene import ROBOT_DESCRIPTION, STANDARD_TOPICS, TF_STATIC
from acquisition.schemas.topics import EVENTS, PRESSURE, SERVO_STATE, STEPPER, TRACKER, session_topics
from models.robot import load_robot

RATES_HZ = {SERVO_STATE: 500, PRESSURE: 250, TRACKER: 40, STEPPER: 20}
T0 = 1_700_000_000_000_000_000  # host ns


@pytest.fixture(scope="module")
def robot():
    return load_robot("vsl")


def random_rows(message: FixedMessage, n: int, rng: np.random.Generator) -> np.ndarray:
    columns = {}
    for f in message.fields:
        shape = (n, f.count) if f.count else (n,)
        dtype = np.dtype(PRIMITIVES[f.type])
        if f.type == "bool":
            columns[f.name] = rng.random(shape) < 0.5
        elif dtype.kind == "f":
            columns[f.name] = rng.normal(size=shape)
        else:
            info = np.iinfo(dtype)
            columns[f.name] = rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)
    return message.pack(columns)


@dataclass
class Stream:
    log_time: np.ndarray
    publish_time: np.ndarray
    rows: np.ndarray


def make_streams(robot, seconds: float, rng: np.random.Generator) -> dict[str, Stream]:
    topics = session_topics(robot)
    out = {}
    for name, hz in RATES_HZ.items():
        n = int(seconds * hz)
        period = 1e9 / hz
        log_time = T0 + (np.arange(n) * period + rng.uniform(0, 0.3 * period, n)).astype(np.int64)
        publish = log_time - rng.integers(0, 1_000_000, n)  # device stamps, a bit earlier
        out[name] = Stream(log_time, publish, random_rows(topics[name].message, n, rng))
    return out


def make_events(seconds: float) -> list[tuple[int, Event]]:
    events = [(T0, Event(EventKind.SESSION_START, label="s1"))]
    for k in range(int(seconds)):
        events.append((T0 + k * 10**9 + 5, Event(EventKind.REPETITION_START, k, label=f"rep{k}", text="é ✓")))
        events.append((T0 + k * 10**9 + 7, Event(EventKind.PAYLOAD, k, 0.05 * k)))
    events.append((T0 + int(seconds * 1e9), Event(EventKind.SESSION_END, text="")))
    return events


def write_session(writer: SessionWriter, streams, events, batch_s: float = 0.1, flush_each=False) -> None:
    """Feed the streams batch by batch in log-time order, events interleaved, as the recorder does."""
    end = max(int(s.log_time[-1]) for s in streams.values()) + 1
    pending = sorted(events, key=lambda e: e[0])
    edges = np.arange(T0, end + int(batch_s * 1e9), int(batch_s * 1e9))
    for lo, hi in itertools.pairwise(edges):
        while pending and pending[0][0] < hi:
            t, event = pending.pop(0)
            writer.event(event, t)
        for name, s in streams.items():
            i, j = np.searchsorted(s.log_time, [lo, hi])
            if j > i:
                writer.write(name, s.log_time[i:j], s.rows[i:j], s.publish_time[i:j])
        if flush_each:
            writer.flush()
    for t, event in pending:
        writer.event(event, t)


def still_clock() -> float:
    return 0.0  # flushes only when the test asks


def file_messages(path) -> list[tuple[str, int, int, int, bytes]]:
    """(topic, log_time, publish_time, sequence, data) of every message, in file order (linear read)."""
    topics, out = {}, []
    with open(path, "rb") as f:
        for record in StreamReader(f).records:
            if hasattr(record, "topic") and hasattr(record, "message_encoding"):
                topics[record.id] = record.topic
            elif isinstance(record, Message):
                out.append(
                    (
                        topics[record.channel_id],
                        record.log_time,
                        record.publish_time,
                        record.sequence,
                        record.data,
                    )
                )
    return out


def assert_valid_indexed(path) -> object:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        count = sum(1 for _ in reader.iter_messages(log_time_order=False))
        assert count == summary.statistics.message_count
    return summary


# --------------------------------------------------------------------------------------- one part
@pytest.fixture(scope="module")
def session(robot, tmp_path_factory):
    directory = tmp_path_factory.mktemp("session")
    rng = np.random.default_rng(1)
    streams = make_streams(robot, 2.0, rng)
    events = make_events(2.0)
    with SessionWriter(
        directory, robot, "s1", experiment="test", metadata={"operator": "pytest"}, chunk_size=16384,
        clock=still_clock,
    ) as w:  # fmt: skip
        w.note_received(SERVO_STATE, len(streams[SERVO_STATE].rows) + 5)
        w.note_dropped(SERVO_STATE, 5)
        write_session(w, streams, events)
    return directory, w, streams, events


def test_single_part_written(session):
    directory, w, _, _ = session
    assert [p.name for p in w.parts] == ["s1_000.mcap"]
    assert sorted(p.name for p in directory.iterdir()) == ["s1_000.mcap", SESSION_CARD]


def test_fast_reader_matches_written_values(session):
    directory, _, streams, _ = session
    data = read_fixed_topics(directory / "s1_000.mcap")
    for name, s in streams.items():
        got = data[name]
        assert len(got) == len(s.rows)
        np.testing.assert_array_equal(got.log_time, s.log_time)
        np.testing.assert_array_equal(got.publish_time, s.publish_time)
        assert got.rows.dtype == s.rows.dtype
        assert got.rows.tobytes() == s.rows.tobytes()
    for name in set(data) - set(streams):  # topics of the robot never written
        assert len(data[name]) == 0 and data[name].rows.dtype == data[name].message.dtype
    assert EVENTS not in data  # variable-size: read with the generic reader
    assert set(read_fixed_topics(directory / "s1_000.mcap", topics=[TRACKER])) == {TRACKER}


def test_standard_reader_matches_fast_reader(session):
    directory, _, streams, events = session
    fast = read_fixed_topics(directory / "s1_000.mcap")
    seen: dict[str, list] = {}
    with open(directory / "s1_000.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            seen.setdefault(channel.topic, []).append((message, decoded, schema))
    # beside the measured topics, the arm for a viewer (tests/test_foxglove_export.py checks those)
    assert set(seen) - STANDARD_TOPICS == set(streams) | {EVENTS}
    assert {ROBOT_DESCRIPTION, TF_STATIC} <= set(seen)
    with open(directory / "s1_000.mcap", "rb") as f:  # the viewer's topics in chunks of their own
        summary = make_reader(f).get_summary()
    topics = {cid: c.topic for cid, c in summary.channels.items()}
    kinds = [{topics[c] in STANDARD_TOPICS for c in ci.message_index_offsets} for ci in summary.chunk_indexes]
    assert {True} in kinds and {False} in kinds and all(len(k) == 1 for k in kinds)
    for name, items in seen.items():
        if name == EVENTS or name in STANDARD_TOPICS:
            continue
        td = fast[name]
        assert len(items) == len(td)
        np.testing.assert_array_equal([m.log_time for m, _, _ in items], td.log_time)
        np.testing.assert_array_equal([m.publish_time for m, _, _ in items], td.publish_time)
        np.testing.assert_array_equal([m.sequence for m, _, _ in items], np.arange(len(td)))
        for f in td.message.fields:
            values = [getattr(d, f.name) for _, d, _ in items]
            if values and isinstance(values[0], bytes):
                values = [np.frombuffer(v, PRIMITIVES[f.type]) for v in values]
            np.testing.assert_array_equal(
                np.asarray(values, PRIMITIVES[f.type]), td.rows[f.name], err_msg=name
            )
        assert items[0][2].name == td.message.name
    got_events = [(m.log_time, d) for m, d, _ in seen[EVENTS]]
    assert [t for t, _ in got_events] == sorted(t for t, _ in events)
    for (_, d), (_, e) in zip(got_events, sorted(events, key=lambda x: x[0]), strict=True):
        assert (d.kind, d.index, d.label, d.text) == (int(e.kind), e.index, e.label, e.text)
        assert (math.isnan(d.value) and math.isnan(e.value)) or d.value == e.value


def test_summary_statistics(session):
    directory, _, streams, events = session
    summary = assert_valid_indexed(directory / "s1_000.mcap")
    stats = summary.statistics
    every = {summary.channels[cid].topic: n for cid, n in stats.channel_message_counts.items()}
    by_topic = {k: n for k, n in every.items() if k not in STANDARD_TOPICS}  # the measured ones
    expected = {name: len(s.rows) for name, s in streams.items()} | {EVENTS: len(events)}
    assert {k: v for k, v in by_topic.items() if v} == expected
    assert all(v == 0 for k, v in by_topic.items() if k not in expected)
    assert stats.message_count == sum(expected.values()) + sum(every[k] for k in STANDARD_TOPICS)
    all_times = np.concatenate([s.log_time for s in streams.values()] + [[t for t, _ in events]])
    assert stats.message_start_time == all_times.min() and stats.message_end_time == all_times.max()
    assert stats.chunk_count == len(summary.chunk_indexes) > 1
    assert stats.schema_count == len(summary.schemas) and stats.channel_count == len(summary.channels)
    with open(directory / "s1_000.mcap", "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert header.profile == "ros2"
    assert metadata[SESSION_METADATA]["session_id"] == "s1"
    assert metadata[SESSION_METADATA]["operator"] == "pytest"
    assert metadata[SESSION_METADATA]["robot"] == "vsl"
    assert metadata[SESSION_METADATA]["part"] == "0"
    assert json.loads(metadata[COUNTERS_METADATA][SERVO_STATE])["written"] == len(streams[SERVO_STATE].rows)


def test_session_card(session):
    directory, _, streams, events = session
    card = json.loads((directory / SESSION_CARD).read_text())
    assert card["status"] == "complete"
    assert card["parts"] == ["s1_000.mcap"]
    assert card["session_id"] == "s1" and card["experiment"] == "test" and card["robot"] == "vsl"
    assert "robot_description" not in card
    servo = card["counters"][SERVO_STATE]
    n = len(streams[SERVO_STATE].rows)
    assert servo == {
        "expected": n + 5, "received": n + 5, "lost": 0, "written": n, "dropped": 5, "gaps": 0,
        "first_ns": int(streams[SERVO_STATE].log_time[0]), "last_ns": int(streams[SERVO_STATE].log_time[-1]),
    }  # fmt: skip
    for name, s in streams.items():
        if name != SERVO_STATE:  # never noted: received follows written
            assert card["counters"][name]["written"] == card["counters"][name]["received"] == len(s.rows)
    assert card["counters"][EVENTS]["written"] == len(events)


def test_card_says_recording_while_open(robot, tmp_path):
    w = SessionWriter(tmp_path, robot, "s2", clock=still_clock)
    w.open()
    assert json.loads((tmp_path / SESSION_CARD).read_text())["status"] == "recording"
    w.close()
    assert json.loads((tmp_path / SESSION_CARD).read_text())["status"] == "complete"


def test_writer_rejects_bad_input(robot, tmp_path):
    topics = session_topics(robot)
    rows = topics[SERVO_STATE].message.empty(3)
    with SessionWriter(tmp_path, robot, "s3", clock=still_clock) as w:
        with pytest.raises(ValueError, match="not"):
            w.write(SERVO_STATE, np.arange(3), topics[PRESSURE].message.empty(3))
        with pytest.raises(ValueError, match="log times"):
            w.write(SERVO_STATE, np.arange(2), rows)
        with pytest.raises(ValueError, match="no topic"):
            w.write("/nope", np.arange(3), rows)
        with pytest.raises(ValueError, match="event"):
            w.write(EVENTS, np.arange(3), rows)
    with pytest.raises(RuntimeError):
        w.write(SERVO_STATE, np.arange(3), rows)


# ----------------------------------------------------------------------------------------- rotation
def check_parts(w: SessionWriter, streams, events) -> None:
    assert len(w.parts) >= 3
    per_topic: dict[str, list] = {}
    for k, path in enumerate(w.parts):
        assert path.name == f"{w.session_id}_{k:03d}.mcap"
        assert_valid_indexed(path)
        with open(path, "rb") as f:
            metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
        assert metadata[SESSION_METADATA]["session_id"] == w.session_id
        assert metadata[SESSION_METADATA]["part"] == str(k)
        assert (COUNTERS_METADATA in metadata) == (k == len(w.parts) - 1)
        for topic, log_time, publish, seq, data in file_messages(path):
            per_topic.setdefault(topic, []).append((seq, log_time, publish, data))
    for name, s in streams.items():
        got = sorted(per_topic[name])
        assert [g[0] for g in got] == list(range(len(s.rows)))  # every message exactly once
        np.testing.assert_array_equal([g[1] for g in got], s.log_time)
        np.testing.assert_array_equal([g[2] for g in got], s.publish_time)
        assert b"".join(g[3] for g in got) == s.rows.tobytes()
    assert sorted(g[1] for g in per_topic[EVENTS]) == sorted(t for t, _ in events)
    card = json.loads((w.directory / SESSION_CARD).read_text())
    assert card["parts"] == [p.name for p in w.parts] and card["status"] == "complete"


def test_rotation_by_duration(robot, tmp_path):
    rng = np.random.default_rng(2)
    streams, events = make_streams(robot, 5.0, rng), make_events(5.0)
    with SessionWriter(
        tmp_path, robot, "rot", chunk_size=8192, clock=still_clock, rotation=RotationPolicy(None, 1.5)
    ) as w:
        write_session(w, streams, events, batch_s=0.25)
    check_parts(w, streams, events)
    for path in w.parts[:-1]:  # rotation is checked per batch (0.25 s): parts span max_seconds ± a batch
        summary = assert_valid_indexed(path)
        span = (summary.statistics.message_end_time - summary.statistics.message_start_time) / 1e9
        assert 1.5 - 0.25 <= span < 1.5 + 0.25


def test_rotation_by_size(robot, tmp_path):
    rng = np.random.default_rng(3)
    streams, events = make_streams(robot, 3.0, rng), make_events(3.0)
    with SessionWriter(
        tmp_path, robot, "big", chunk_size=4096, clock=still_clock, rotation=RotationPolicy(30_000, None)
    ) as w:
        write_session(w, streams, events, batch_s=0.05)
    check_parts(w, streams, events)


# ----------------------------------------------------------------------------------------- recovery
@pytest.fixture(scope="module")
def torn_source(robot, tmp_path_factory):
    """A finished part written in small, flushed chunks, and its messages in file order."""
    directory = tmp_path_factory.mktemp("torn")
    rng = np.random.default_rng(4)
    streams, events = make_streams(robot, 1.0, rng), make_events(1.0)
    with SessionWriter(directory, robot, "t", chunk_size=2048, clock=still_clock) as w:
        write_session(w, streams, events, batch_s=0.05, flush_each=True)
    path = w.parts[0]
    return path.read_bytes(), file_messages(path)


def cut_points(size: int) -> list[int]:
    rng = np.random.default_rng(5)
    fixed = [0, 3, 8, 9, 40, 300, size // 5, size // 3, size // 2, 2 * size // 3, size - 40, size - 1]
    return sorted(set(fixed) | set(rng.integers(0, size, 8).tolist()))


def test_truncated_files_recover_to_a_prefix(torn_source, tmp_path):
    data, original = torn_source
    previous = -1
    for cut in cut_points(len(data)):
        source = tmp_path / f"cut{cut}.mcap"
        source.write_bytes(data[:cut])
        report = recover(source)
        assert report.output == tmp_path / f"cut{cut}{RECOVERED_SUFFIX}"
        assert report.torn == (cut < len(data) - 8), cut  # only the closing magic cut: footer was read
        assert bool(report.reason) == report.torn
        assert source.read_bytes() == data[:cut]  # the source is never touched
        summary = assert_valid_indexed(report.output)
        recovered = file_messages(report.output)
        assert report.messages == len(recovered) == summary.statistics.message_count
        assert recovered == original[: len(recovered)], f"cut at {cut}: not a prefix"
        assert len(recovered) >= previous  # more bytes never give fewer messages
        previous = len(recovered)
        fast = read_fixed_topics(report.output)  # the fast reader reads a foreign writer's file too
        for topic, td in fast.items():
            mine = [m for m in recovered if m[0] == topic]
            assert td.log_time.tolist() == [m[1] for m in mine]
            assert td.rows.tobytes() == b"".join(m[4] for m in mine)
    assert previous > len(original) // 2  # late cuts keep most of the file
    with open(tmp_path / f"cut{len(data) - 1}{RECOVERED_SUFFIX}", "rb") as f:
        metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert metadata[SESSION_METADATA]["session_id"] == "t"  # metadata survives recovery


def test_complete_file_recovers_whole(torn_source, tmp_path):
    data, original = torn_source
    source = tmp_path / "whole.mcap"
    source.write_bytes(data)
    report = recover(source, tmp_path / "out.mcap")
    assert not report.torn and report.reason == ""
    assert report.output == tmp_path / "out.mcap"
    assert file_messages(report.output) == original
    # every channel, even unused ones: the measured topics and the arm's
    assert report.channels == len(session_topics(load_robot("vsl"))) + len(STANDARD_TOPICS)


def test_recover_never_overwrites_its_source(torn_source, tmp_path):
    data, _ = torn_source
    source = tmp_path / "src.mcap"
    source.write_bytes(data[: len(data) // 2])
    for target in (source, tmp_path / "." / "src.mcap", str(source)):
        with pytest.raises(ValueError, match="never overwrites"):
            recover(source, target)
    link = tmp_path / "link.mcap"
    link.symlink_to(source)
    with pytest.raises(ValueError):
        recover(link, source)
    assert source.read_bytes() == data[: len(data) // 2]


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all\n" * 40, bytes(range(256)) * 4])
def test_non_mcap_file_recovers_to_an_empty_valid_file(tmp_path, content):
    source = tmp_path / "junk.mcap"
    source.write_bytes(content)
    report = recover(source)
    assert report.messages == 0 and report.channels == 0
    assert report.torn and report.reason  # says why it stopped (bad magic / end of file)
    summary = assert_valid_indexed(report.output)
    assert summary.statistics.message_count == 0
    assert read_fixed_topics(report.output) == {}
    assert source.read_bytes() == content


def test_fast_reader_refuses_a_torn_file(torn_source, tmp_path):
    data, _ = torn_source
    source = tmp_path / "torn.mcap"
    source.write_bytes(data[: len(data) // 2])
    with pytest.raises(SchemaError):
        read_fixed_topics(source)


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_fast_reader_says_a_torn_file_needs_recovery(torn_source, tmp_path, fraction):
    data, _ = torn_source
    source = tmp_path / "torn.mcap"
    source.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(SchemaError, match="recover"):
        read_fixed_topics(source)


def test_recover_never_overwrites_a_hard_linked_source(torn_source, tmp_path):
    data, _ = torn_source
    source = tmp_path / "src.mcap"
    source.write_bytes(data[: len(data) // 2])
    alias = tmp_path / "alias.mcap"
    alias.hardlink_to(source)
    try:
        recover(source, alias)
    except ValueError:
        pass
    assert source.read_bytes() == data[: len(data) // 2]


def test_writer_rejects_publish_times_of_the_wrong_length(robot, tmp_path):
    rows = session_topics(robot)[SERVO_STATE].message.empty(5)
    with SessionWriter(tmp_path, robot, "p", clock=still_clock) as w:
        with pytest.raises(ValueError):
            w.write(SERVO_STATE, np.arange(5), rows, publish_time_ns=np.arange(1))
