"""Damaged chunks: a bit flipped in a recorded chunk, compressed or not, is caught by the CRC or the
index check and named (file, chunk offset); never read as another value. Every reader says so: the fast
path, the build (a warning per chunk, with what it lost), `sessions list/info/recover` and the export
(one error line)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from acquisition.recorder.foxglove_export import export_foxglove
from acquisition.recorder.sessions import SessionStore
from acquisition.schemas import mcap_reader
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.mcap_reader import DamagedChunkError
from pipeline.ingest import ingest_session
from twin.runner import simulate_experiment

FLIPS = 160  # positions flipped per region, spread evenly over it (deterministic)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """One small twin campaign session (zstd chunks, as the recorder writes them): its session folder."""
    root = tmp_path_factory.mktemp("recorded")
    simulate_experiment(
        "campaign", SessionStore(root / "sessions"), seed=3, benches=1, overrides={"points": 20}
    )
    (session,) = sorted((root / "sessions").iterdir())
    return session


def _part(session: Path) -> Path:
    (part,) = sorted(session.glob("*.mcap"))
    return part


def _uncompressed_copy(source: Path, output: Path) -> None:
    """The same records written again with uncompressed chunks (the spec allows them; CRCs on)."""
    with open(source, "rb") as f, open(output, "wb") as out:
        writer = Writer(out, compression=CompressionType.NONE, chunk_size=1 << 18)
        writer.start(profile="ros2", library="test")
        schemas, channels = {}, {}
        for r in StreamReader(f, validate_crcs=True).records:
            if isinstance(r, Schema) and r.id not in schemas:  # the summary repeats schemas and channels
                schemas[r.id] = writer.register_schema(r.name, r.encoding, r.data)
            elif isinstance(r, Channel) and r.id not in channels:
                channels[r.id] = writer.register_channel(r.topic, r.message_encoding, schemas[r.schema_id],
                                                         r.metadata)  # fmt: skip
            elif isinstance(r, Message):
                writer.add_message(channels[r.channel_id], r.log_time, r.data, r.publish_time, r.sequence)
            elif isinstance(r, Metadata):
                writer.add_metadata(r.name, r.metadata)
            elif isinstance(r, Attachment):
                writer.add_attachment(r.log_time, r.create_time, r.name, r.media_type, r.data)
        writer.finish()


def _chunks(path: Path):
    with open(path, "rb") as f:
        summary = mcap_reader.read_summary(f)
    return summary, sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def _values(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, bytes]]:
    return {t: (d.log_time, d.publish_time, d.rows.tobytes()) for t, d in read_fixed_topics(path).items()}


def _flip_all(path: Path, lo: int, hi: int, scratch: Path) -> tuple[int, int]:
    """Flip one bit at each of FLIPS positions spread over bytes [lo, hi) of ``path``, one file each; every
    flip must raise a DamagedChunkError naming the file and a chunk offset, or read back exactly the original
    values (a harmless bit). Returns (caught, harmless)."""
    original, data = _values(path), path.read_bytes()
    _, chunks = _chunks(path)
    offsets = {c.chunk_start_offset for c in chunks}
    caught = harmless = 0
    flipped = scratch / path.name
    for k, at in enumerate(np.linspace(lo, hi - 1, FLIPS).astype(int).tolist()):
        b = bytearray(data)
        b[at] ^= 1 << (k % 8)
        flipped.write_bytes(bytes(b))
        try:
            values = _values(flipped)
        except DamagedChunkError as exc:
            assert str(flipped) in str(exc) and exc.damage.offset in offsets, (at, str(exc))
            assert f"damaged chunk at byte {exc.damage.offset}" in str(exc)
            caught += 1
            continue
        assert values.keys() == original.keys(), at
        for topic, (log_time, publish, rows) in values.items():  # the same values, bit for bit
            assert np.array_equal(log_time, original[topic][0]), (at, topic)
            assert np.array_equal(publish, original[topic][1]), (at, topic)
            assert rows == original[topic][2], (at, topic)
        harmless += 1
    return caught, harmless


@pytest.mark.slow
def test_flips_in_a_compressed_chunk_are_caught_and_named(recorded, tmp_path):
    part = _part(recorded)
    _, chunks = _chunks(part)
    c = chunks[1]  # a chunk in the middle: the record's header fields, then its zstd frame
    caught, harmless = _flip_all(part, c.chunk_start_offset, c.chunk_start_offset + c.chunk_length, tmp_path)
    assert caught + harmless == FLIPS and caught >= FLIPS * 3 // 4, (caught, harmless)


@pytest.mark.slow
def test_flips_in_an_uncompressed_chunk_are_all_caught(recorded, tmp_path):
    plain = tmp_path / "plain.mcap"
    _uncompressed_copy(_part(recorded), plain)
    _, chunks = _chunks(plain)
    assert {c.compression for c in chunks} == {""} and len(chunks) > 2
    assert {t: v[0].tolist() for t, v in _values(plain).items()} == {
        t: v[0].tolist() for t, v in _values(_part(recorded)).items()
    }
    c = chunks[1]
    records_at = c.chunk_start_offset + c.chunk_length - c.compressed_size  # the records, stored as they are
    (tmp_path / "flips").mkdir()
    caught, harmless = _flip_all(plain, records_at, records_at + c.compressed_size, tmp_path / "flips")
    assert (caught, harmless) == (FLIPS, 0)  # a CRC32 catches every single-bit error


@pytest.mark.slow
def test_flips_in_a_chunk_s_message_index_are_caught_or_harmless(recorded, tmp_path):
    """The message indexes lie outside the chunk's CRC: each entry is checked against the record it names."""
    part = _part(recorded)
    _, chunks = _chunks(part)
    c = chunks[1]
    lo = min(c.message_index_offsets.values())
    caught, harmless = _flip_all(part, lo, lo + c.message_index_length, tmp_path)
    assert caught + harmless == FLIPS and caught >= FLIPS // 2, (caught, harmless)


def _damaged_session(recorded: Path, lab: Path) -> tuple[Path, int]:
    """A copy of the session under ``lab/sessions`` with one bit flipped in its second chunk's zstd frame:
    (the session folder, that chunk's offset)."""
    session = lab / "sessions" / recorded.name
    shutil.copytree(recorded, session)
    part = _part(session)
    _, chunks = _chunks(part)
    c = chunks[1]
    data = bytearray(part.read_bytes())
    data[c.chunk_start_offset + c.chunk_length - c.compressed_size // 2] ^= 0x04
    part.write_bytes(bytes(data))
    return session, c.chunk_start_offset


def test_ingest_leaves_a_damaged_chunk_out_and_says_what_it_lost(recorded, tmp_path):
    session, offset = _damaged_session(recorded, tmp_path)
    whole, damaged = ingest_session(recorded), ingest_session(session)
    lines = [w for w in damaged.report.warnings if "damaged chunk" in w]
    assert len(lines) == 1 and f"byte {offset}" in lines[0] and "messages lost" in lines[0], lines
    _, chunks = _chunks(_part(recorded))
    c = chunks[1]
    for topic, df in whole.streams.items():
        t = df["log_time"].to_numpy()
        kept = t[(t < c.message_start_time) | (t > c.message_end_time)]
        inside = damaged.streams[topic]["log_time"].to_numpy()
        assert set(inside.tolist()) <= set(t.tolist()), topic  # nothing invented
        assert set(kept.tolist()) <= set(inside.tolist()), topic  # only that chunk's messages are lost


def _cli(lab: Path, *args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def _said(done: subprocess.CompletedProcess) -> list[str]:
    return (done.stdout + done.stderr).strip().splitlines()


@pytest.mark.slow
def test_every_command_names_a_damaged_chunk(recorded, tmp_path):
    lab = tmp_path / "lab"
    session, offset = _damaged_session(recorded, lab)
    where = f"{_part(session).name}: damaged chunk at byte {offset}"
    for args in (("sessions", "list"), ("sessions", "info", session.name)):
        done = _cli(lab, *args)
        warnings = [ln for ln in _said(done) if ln.startswith("warning:")]
        assert done.returncode == 0 and len(warnings) == 1 and where in warnings[0], (args, _said(done))
    for args in (("sessions", "recover", session.name), ("sessions", "export", session.name, "--foxglove")):
        done = _cli(lab, *args)
        said = _said(done)
        assert done.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), (args, said)
        assert where in said[0], (args, said)
    assert not list(lab.rglob("*.partial")) and not (lab / "exports").exists()
    done = _cli(lab, "build", "--name", "campaign")
    warnings = [ln for ln in _said(done) if ln.startswith("warning:")]
    assert done.returncode == 0 and len(warnings) == 1, _said(done)
    assert session.name in warnings[0] and where in warnings[0] and "messages lost" in warnings[0]


@pytest.mark.slow
@pytest.mark.parametrize("rate", ["inf", "nan", "0", "-1", "1e9"])
def test_export_refuses_a_rate_out_of_bounds_in_one_line(recorded, tmp_path, rate):
    lab = tmp_path / "lab"
    shutil.copytree(recorded, lab / "sessions" / recorded.name)
    out = tmp_path / "x.mcap"
    done = _cli(lab, "sessions", "export", recorded.name, "--foxglove", "--out", str(out), "--rate-hz", rate)
    said = _said(done)
    assert done.returncode == 2 and len(said) == 1 and said[0].startswith("error: --rate-hz"), said
    assert not out.exists() and not list(tmp_path.rglob("*.partial"))


def test_an_export_that_fails_leaves_no_partial_file(recorded, tmp_path):
    lab = tmp_path / "lab"
    shutil.copytree(recorded, lab / "sessions" / recorded.name)
    target = tmp_path / "out"
    target.mkdir()  # the file cannot be renamed onto a directory: the write fails at its very end
    with pytest.raises(OSError):
        export_foxglove(lab / "sessions" / recorded.name, target)
    assert not list(tmp_path.rglob("*.partial"))
    done = _cli(lab, "sessions", "export", recorded.name, "--foxglove", "--out", str(target))
    said = _said(done)
    assert done.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), said
    assert not list(tmp_path.rglob("*.partial")) and not any(target.iterdir())
