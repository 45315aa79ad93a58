"""The MCAP container is known in one place (acquisition/schemas/mcap_reader.py and mcap_writer.py): files the
batch writer makes read back through it, a torn file is walked to its tear by the one walk, and no other
module of vslab imports the mcap package or spells the MCAP magic."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from acquisition.schemas import mcap_reader
from acquisition.schemas.mcap_reader import MAGIC, Message, Metadata, RecordWalk
from acquisition.schemas.mcap_writer import BatchMcapWriter, copy_readable

ROOT = Path(__file__).resolve().parents[1]
MCAP_MODULES = {"acquisition/schemas/mcap_reader.py", "acquisition/schemas/mcap_writer.py"}
# bench/ is left out on purpose: the benchmarks time vslab against the mcap package's own reader and writer
PACKAGES = ("acquisition", "twin", "pipeline", "analysis", "models", "vslab")


def _write(path: Path, n: int = 1000, chunk_size: int = 4096, compress_in=None) -> None:
    with open(path, "wb") as f:
        w = BatchMcapWriter(f, chunk_size=chunk_size, compress_in=compress_in)
        w.start(profile="ros2", library="test")
        schema = w.register_schema("t/msg/Fixed", "ros2msg", b"int64 x")
        fixed = w.register_channel("/fixed", "cdr", schema)
        other = w.register_channel("/other", "cdr", schema)
        w.add_metadata("vslab.session", {"session_id": "s"})
        t = np.arange(n, dtype=np.uint64) * 1000 + 5
        payload = np.arange(n * 12, dtype=np.uint64).astype(np.uint8).reshape(n, 12)
        w.add_batch(fixed, t, t + 1, np.arange(n, dtype=np.uint32), payload)
        for i in range(3):
            w.add_message(other, 10 + i, b"x" * (i + 1), 20 + i, i)
        w.finish()


def test_what_the_batch_writer_writes_reads_back_by_chunk_and_by_index(tmp_path):
    path = tmp_path / "a.mcap"
    _write(path)
    with open(path, "rb") as f:
        assert mcap_reader.read_magic(f) == MAGIC
        summary = mcap_reader.read_summary(f)
        ids = {c.topic: cid for cid, c in summary.channels.items()}
        parts = mcap_reader.fixed_size_messages(f, summary, {ids["/fixed"]: 12})[ids["/fixed"]]
        log_time = np.concatenate([p[0] for p in parts])
        payload = np.concatenate([p[2] for p in parts])
        assert len(parts) > 1  # several chunks
        assert np.array_equal(log_time, np.arange(1000) * 1000 + 5)
        assert np.array_equal(np.concatenate([p[1] for p in parts]), log_time + 1)
        assert np.array_equal(payload.reshape(-1), np.arange(12000, dtype=np.uint64).astype(np.uint8))
        other = sorted(mcap_reader.indexed_messages(f, summary, {ids["/other"]}), key=lambda m: m[1])
        assert [(m[1], m[2], m[3]) for m in other] == [(10, 20, b"x"), (11, 21, b"xx"), (12, 22, b"xxx")]
        assert dict(mcap_reader.metadata_records(f)) == {"vslab.session": {"session_id": "s"}}
        assert dict(mcap_reader.metadata_records(f, summary)) == {"vslab.session": {"session_id": "s"}}
        spans = mcap_reader.topic_spans(f)
        assert spans["/fixed"] == (1000, 5, 999_005) and spans["/other"] == (3, 10, 12)


def test_chunks_compressed_in_threads_make_the_same_file_byte_for_byte(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    _write(tmp_path / "here.mcap", n=20_000)
    with ThreadPoolExecutor(2) as pool:
        _write(tmp_path / "threads.mcap", n=20_000, compress_in=pool)
    here, threads = (tmp_path / "here.mcap").read_bytes(), (tmp_path / "threads.mcap").read_bytes()
    assert here.count(b"t/msg/Fixed") == 2 and len(here) > 100_000  # many chunks: several in flight at once
    assert threads == here


def test_derived_channels_have_chunks_of_their_own_and_read_back_in_time_order(tmp_path):
    """A viewer's channels (derived from the measured ones) never share a chunk with a measured channel, so a
    reader of the measured channels skips their bytes; the mcap package reads the interleaved file in time
    order."""
    from mcap.reader import make_reader

    path, n = tmp_path / "d.mcap", 3000
    with open(path, "wb") as f:
        w = BatchMcapWriter(f, chunk_size=4096)
        w.start(profile="ros2", library="test")
        schema = w.register_schema("t/msg/Fixed", "ros2msg", b"int64 x")
        measured = w.register_channel("/measured", "cdr", schema)
        derived = w.register_channel("/derived", "cdr", schema, derived=True)
        t = np.arange(n, dtype=np.uint64) * 1000
        for lo in range(0, n, 100):  # the two written in turns, as a recorder writes them
            now, seq = t[lo : lo + 100], np.arange(lo, lo + 100, dtype=np.uint32)
            w.add_batch(measured, now, now, seq, np.zeros((100, 8), np.uint8))
            w.add_batch(derived, now + 1, now + 1, seq, np.ones((100, 8), np.uint8))
        w.finish()
    with open(path, "rb") as f:
        mcap_reader.read_magic(f)
        summary = mcap_reader.read_summary(f)
        holding = [set(ci.message_index_offsets) for ci in summary.chunk_indexes]
        assert len(holding) > 10 and all(len(h) == 1 for h in holding)
        assert {derived} in holding and {measured} in holding
        parts = mcap_reader.fixed_size_messages(f, summary, {measured: 8})[measured]
        assert np.array_equal(np.concatenate([p[0] for p in parts]), t.astype(np.int64))
    with open(path, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=True)]
    assert len(times) == 2 * n and times == sorted(times)


def test_a_message_of_the_wrong_size_is_refused(tmp_path):
    path = tmp_path / "a.mcap"
    _write(path)
    with open(path, "rb") as f:
        summary = mcap_reader.read_summary(f)
        ids = {c.topic: cid for cid, c in summary.channels.items()}
        with pytest.raises(mcap_reader.SchemaError, match="not 8 bytes"):
            mcap_reader.fixed_size_messages(f, summary, {ids["/fixed"]: 8})


def test_a_torn_file_is_walked_to_its_tear_and_copied_whole(tmp_path):
    path = tmp_path / "a.mcap"
    _write(path)
    whole = path.read_bytes()
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(whole[: len(whole) * 2 // 3])
    with open(torn, "rb") as f:
        assert mcap_reader.read_summary(f) is None and mcap_reader.topic_spans(f) is None
        walk = RecordWalk(f)
        records = list(walk)
    assert not walk.complete and walk.reason
    messages = [r for r in records if isinstance(r, Message)]
    assert 0 < len(messages) < 1003
    assert any(isinstance(r, Metadata) for r in records)
    with open(torn, "rb") as f, open(tmp_path / "mended.mcap", "wb") as out:
        copied, channels, was_torn, reason = copy_readable(f, out, library="test")
    assert (copied, channels, was_torn, reason) == (len(messages), 2, True, walk.reason)
    with open(tmp_path / "mended.mcap", "rb") as f:
        assert mcap_reader.read_summary(f).statistics.message_count == len(messages)
    with open(path, "rb") as f:
        walk = RecordWalk(f)
        assert sum(isinstance(r, Message) for r in walk) == 1003 and walk.complete and walk.reason == ""


def _offences(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [f"import {a.name}" for a in node.names if a.name.split(".")[0] == "mcap"]
        elif (
            isinstance(node, ast.ImportFrom)
            and node.level == 0
            and (node.module or "").split(".")[0] == "mcap"
        ):
            found.append(f"from {node.module} import …")
        elif isinstance(node, ast.Constant) and isinstance(node.value, bytes) and b"MCAP0" in node.value:
            found.append("the MCAP magic")
    return found


def test_no_module_but_the_mcap_modules_knows_the_container():
    offences = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = path.relative_to(ROOT).as_posix()
            if name not in MCAP_MODULES and (found := _offences(path)):
                offences[name] = found
    assert offences == {}, f"MCAP records parsed outside {sorted(MCAP_MODULES)}: {offences}"


def test_the_structural_check_sees_an_offence(tmp_path):
    sneaky = tmp_path / "sneaky.py"
    sneaky.write_text('"""from mcap.reader import x"""\ndef f():\n    from mcap.records import Chunk\n'
                      'MAGIC = b"\\x89MCAP0\\r\\n"\n')  # fmt: skip
    assert _offences(sneaky) == ["from mcap.records import …", "the MCAP magic"]
