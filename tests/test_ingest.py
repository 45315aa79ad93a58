"""Ingest: simulated sessions → tables; generic path = fast path; torn, foreign and incomplete sessions."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mcap.writer import Writer
from mcap_ros2._dynamic import serialize_dynamic

from acquisition.plans.plan import PlanBuilder
from acquisition.recorder.writer import RotationPolicy, SessionWriter
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.fast_read import read_events, read_fixed_topics
from pipeline.clean import OUTLIER, clean
from pipeline.ingest import IngestError, content_hash, ingest_session
from pipeline.tables import EVENT_COLUMNS
from twin.runner import session_id, simulate


@pytest.fixture(scope="module")
def session(vsl, tmp_path_factory) -> Path:
    """One short simulated session (a few seconds of plan time)."""
    b = PlanBuilder("short/ingest", vsl.name, 3, vsl.pneumatics.channels, {"experiment": "short"})
    b.goto([0.0, 0.3, -0.6]).pressure(1.2e5).payload(0.05).wait(0.5)
    b.goto([0.1, 0.5, -0.5], speed=1.0).mark(EventKind.NOTE, text="moved").wait(1.5)
    plan = b.build()
    sessions = tmp_path_factory.mktemp("sessions")
    simulate([plan], vsl, sessions, seed=3)
    return sessions / session_id(plan)


def _part(directory: Path) -> Path:
    (part,) = sorted(directory.glob("*.mcap"))
    return part


def test_simulated_session_gives_one_table_per_topic(session, vsl):
    tables = ingest_session(session)
    fast = read_fixed_topics(_part(session))
    counters = json.loads((session / "session.json").read_text())["counters"]
    assert tables.session_id == session.name and tables.robot == vsl
    assert set(tables.streams) == set(fast) and tables.report.warnings == []
    for topic, data in fast.items():
        df = tables.streams[topic]
        assert len(df) == len(data) == counters[topic]["written"], topic
        np.testing.assert_array_equal(df["log_time"].to_numpy(), data.log_time)
        np.testing.assert_array_equal(df["publish_time"].to_numpy(), data.publish_time)
        assert df["log_time"].dtype == np.int64 and "_cdr_header" not in df.columns
        for f in data.message.fields:
            for i in range(f.count) if f.count else [None]:
                name = f.name if i is None else f"{f.name}_{i}"
                want = data.rows[f.name] if i is None else data.rows[f.name][:, i]
                assert df[name].dtype == want.dtype, name  # bools stay bool, counters stay unsigned
                np.testing.assert_array_equal(df[name].to_numpy(), want)
    tracker = tables.streams[T.TRACKER]
    assert list(tracker.columns)[:4] == ["log_time", "publish_time", "frame", "port_handle"]
    assert {"position_0", "position_2", "quaternion_3", "rms_error"} <= set(tracker.columns)
    servo = tables.streams[T.SERVO_STATE]
    assert servo["moving_0"].dtype == bool and servo["tick_ms"].dtype == np.uint16
    events = read_events(_part(session))
    assert list(tables.events.columns) == list(EVENT_COLUMNS) and len(tables.events) == len(events)
    assert counters[T.EVENTS]["written"] == len(events)
    assert "moved" in set(tables.events["text"]) and EventKind.NOTE in set(tables.events["kind"])
    assert tables.content_hash == content_hash([_part(session)]) and len(tables.content_hash) == 64
    assert "robot_description" not in tables.metadata and tables.metadata["experiment"] == "short"


def test_generic_path_equals_fast_path(session):
    fast = ingest_session(session)
    generic = ingest_session(session, generic_topics=[T.SERVO_STATE, T.TRACKER])
    for topic in (T.SERVO_STATE, T.TRACKER):
        pd.testing.assert_frame_equal(generic.streams[topic], fast.streams[topic], check_dtype=False)
    pd.testing.assert_frame_equal(generic.events, fast.events)


def test_topic_without_fixed_layout_takes_the_generic_path(vsl, tmp_path):
    schema_text = "string name\nfloat64[] samples\nuint8[2] flags\n"
    encode = serialize_dynamic("lab_msgs/msg/Note", schema_text)["lab_msgs/msg/Note"]
    directory = tmp_path / "s1"
    directory.mkdir()
    with open(directory / "s1_000.mcap", "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        w.add_metadata("vslab.session", {"session_id": "s1", "robot_description": vsl.model_dump_json()})
        sid = w.register_schema("lab_msgs/msg/Note", "ros2msg", schema_text.encode())
        cid = w.register_channel("/lab/note", "cdr", sid)
        for k in range(3):
            w.add_message(cid, 10 + k, encode({"name": f"n{k}", "samples": [k, 2.5], "flags": [1, k]}), 5 + k)
        w.finish()
    tables = ingest_session(directory)
    df = tables.streams["/lab/note"]
    assert list(df["name"]) == ["n0", "n1", "n2"] and list(df["samples_1"]) == [2.5] * 3
    assert list(df["flags_1"]) == [0, 1, 2] and list(df["publish_time"]) == [5, 6, 7]
    assert any(T.TRACKER in w for w in tables.report.warnings)  # the robot's streams are missing


def test_torn_part_is_read_up_to_the_tear(session, tmp_path):
    torn = tmp_path / session.name
    torn.mkdir()
    part = _part(session)
    data = part.read_bytes()
    (torn / part.name).write_bytes(data[: int(len(data) * 0.8)])
    before = sorted(p.name for p in torn.iterdir())
    tables = ingest_session(torn)
    assert sorted(p.name for p in torn.iterdir()) == before  # nothing written beside the parts
    assert any("torn" in w for w in tables.report.warnings)
    whole = ingest_session(session)
    for topic, df in whole.streams.items():
        got = tables.streams.get(topic, df.iloc[:0])
        assert len(got) >= 0.5 * len(df), topic
        pd.testing.assert_frame_equal(got, df.iloc[: len(got)], obj=topic)  # a prefix of the whole file
    assert len(tables.events) >= 1


def test_multipart_session_is_read_in_order(vsl, tmp_path):
    topics = {k: v for k, v in T.session_topics(vsl).items() if k != T.TRACKER}
    message = topics[T.PRESSURE].message
    c = vsl.pneumatics.channels
    with SessionWriter(tmp_path, vsl, "m1", topics=topics, rotation=RotationPolicy(max_seconds=1.0)) as w:
        for k in range(5):
            t = (np.arange(10) + 10 * k) * 100_000_000 + 1
            rows = message.pack({"seq": np.arange(10) + 10 * k, "pressure": np.full((10, c), 1e5)})
            w.write(T.PRESSURE, t, rows)
    assert len(list(tmp_path.glob("m1_*.mcap"))) >= 3
    tables = ingest_session(tmp_path)
    assert list(tables.streams[T.PRESSURE]["seq"]) == list(range(50))
    assert any(f"no {T.TRACKER} stream" in w for w in tables.report.warnings)  # a warning, not an error


def test_user_errors_are_one_clear_exception(session, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(IngestError, match="empty directory") as err:
        ingest_session(empty)
    assert err.value.path == empty
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hi")
    with pytest.raises(IngestError, match="no MCAP parts"):
        ingest_session(tmp_path / "notes")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "x_000.mcap").write_bytes(b"PK\x03\x04 a zip file, not a recording")
    with pytest.raises(IngestError, match="not an MCAP file") as err:
        ingest_session(foreign)
    assert err.value.path == foreign / "x_000.mcap"
    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(_part(session), cut / "c_000.mcap")
    (cut / "c_000.mcap").write_bytes((cut / "c_000.mcap").read_bytes()[:20])
    with pytest.raises(IngestError, match="truncated"):
        ingest_session(cut)
    with pytest.raises(IngestError, match="not a session directory"):
        ingest_session(tmp_path / "nowhere")


def test_events_table_when_no_events(vsl, tmp_path):
    with SessionWriter(tmp_path, vsl, "e1") as w:
        w.event(Event(EventKind.PAYLOAD, value=0.1, label="p"), 5)
    tables = ingest_session(tmp_path)
    assert tables.events.iloc[0].to_dict() == {"log_time": 5, "kind": 5, "index": -1, "value": 0.1,
                                               "label": "p", "text": ""}  # fmt: skip
    assert all(len(df) == 0 for df in tables.streams.values())


def test_clean_after_ingest_keeps_a_simulated_session(session):
    tables = ingest_session(session)
    cleaned = clean(tables)
    removed = cleaned.report.removed
    assert set(removed) <= {T.TRACKER}  # the twin sends no duplicates and no pressure spikes
    assert removed.get(T.TRACKER, {}).get(OUTLIER, 0) <= 0.03 * len(tables.streams[T.TRACKER])
    for topic in (T.SERVO_STATE, T.PRESSURE, T.STEPPER, T.TRACKER):
        ticks = cleaned.streams[topic]["device_ticks"].to_numpy()
        assert ticks.dtype == np.int64 and np.all(np.diff(ticks) >= 0), topic
    assert tables.report.removed_total() == 0  # the input's report is not shared
