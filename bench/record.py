"""Recording speed: SessionWriter (numpy-built MCAP records) against mcap's Writer, and the fast reader.

A VSL session's fixed-size topics in their real proportions (servo state 500 Hz, pressure 250 Hz, tracker
40 Hz), fed in batches as the recorder's drain thread does (``--batch-ms``: samples per topic per call, at
several sizes), with the standard topics a session also carries (/tf, /joint_states, /tracker/tip: here no
stepper reports, so no /tf; ``no /tf…``: without them).
The reference writes the same payload bytes with the same log/publish times and sequence numbers through
``mcap.writer.Writer`` (zstd, 1 MiB chunks), one ``add_message`` per message; its payloads are sliced into
``bytes`` before the clock starts, so the figure is the writer alone. Reading compares ``read_fixed_topics``
with ``make_reader(...).iter_messages(log_time_order=False)`` on the SessionWriter's file.
Usage: python bench/record.py [--messages N] [--batch-ms MS[,MS...]]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from acquisition.recorder.writer import RotationPolicy, SessionWriter
from acquisition.schemas.cdr import PRIMITIVES, FixedMessage
from acquisition.schemas.fast_read import read_fixed_topics
from acquisition.schemas.topics import (
    MESSAGE_ENCODING,
    PRESSURE,
    SCHEMA_ENCODING,
    SERVO_STATE,
    TRACKER,
    session_topics,
)
from models.robot import load_robot

RATES_HZ = {SERVO_STATE: 500, PRESSURE: 250, TRACKER: 40}
CHUNK_SIZE = 1 << 20
T0 = 1_700_000_000_000_000_000


def random_rows(message: FixedMessage, n: int, rng: np.random.Generator) -> np.ndarray:
    """Plausible values: smooth-ish floats (so zstd sees realistic entropy), counters, flags."""
    columns = {}
    for f in message.fields:
        shape = (n, f.count) if f.count else (n,)
        dtype = np.dtype(PRIMITIVES[f.type])
        if f.type == "bool":
            columns[f.name] = rng.random(shape) < 0.05
        elif dtype.kind == "f":
            columns[f.name] = np.cumsum(rng.normal(scale=1e-3, size=shape), axis=0)
        elif f.name in ("seq", "frame"):
            columns[f.name] = np.arange(n) % np.iinfo(dtype).max
        else:
            columns[f.name] = rng.integers(0, min(np.iinfo(dtype).max, 2**15), size=shape, dtype=dtype)
    return message.pack(columns)


def build(messages: int, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """topic → (log_time ns, rows) for ``messages`` messages in all, at the topics' rates."""
    rng = np.random.default_rng(seed)
    topics = session_topics(load_robot("vsl"))
    seconds = messages / sum(RATES_HZ.values())
    out = {}
    for name, hz in RATES_HZ.items():
        n = round(seconds * hz)
        period = 1e9 / hz
        log_time = T0 + (np.arange(n) * period + rng.uniform(0, 0.2 * period, n)).astype(np.int64)
        out[name] = (log_time, random_rows(topics[name].message, n, rng))
    return out


def batches(data, batch_ms: float):
    """(topic, lo, hi) slices in the order the recorder would write them."""
    step = int(batch_ms * 1e6)
    end = max(int(t[-1]) for t, _ in data.values()) + 1
    bounds = {name: np.searchsorted(t, np.arange(T0, end + step, step)) for name, (t, _) in data.items()}
    n_batches = len(next(iter(bounds.values()))) - 1
    for k in range(n_batches):
        for name, b in bounds.items():
            if b[k + 1] > b[k]:
                yield name, int(b[k]), int(b[k + 1])


def write_session(directory: Path, data, order, standard: bool = True) -> tuple[float, Path]:
    robot = load_robot("vsl")
    start = time.perf_counter()
    with SessionWriter(
        directory, robot, "bench", chunk_size=CHUNK_SIZE, rotation=RotationPolicy(None, None),
        standard_topics=standard,
    ) as w:  # fmt: skip
        for name, lo, hi in order:
            log_time, rows = data[name]
            w.write(name, log_time[lo:hi], rows[lo:hi])
    return time.perf_counter() - start, w.parts[0]


def write_reference(path: Path, data, order) -> float:
    topics = session_topics(load_robot("vsl"))
    payloads = {}
    for name, (_, rows) in data.items():  # outside the clock: the reference gets ready-made bytes
        raw, size = rows.tobytes(), rows.dtype.itemsize
        payloads[name] = [raw[i : i + size] for i in range(0, len(raw), size)]
    times = {name: t.tolist() for name, (t, _) in data.items()}
    start = time.perf_counter()
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="bench")
        channels = {}
        for name, topic in topics.items():
            schema = writer.register_schema(topic.schema_name, SCHEMA_ENCODING, topic.schema_text.encode())
            channels[name] = writer.register_channel(name, MESSAGE_ENCODING, schema)
        for name, lo, hi in order:
            channel, pay, tim = channels[name], payloads[name], times[name]
            for i in range(lo, hi):
                writer.add_message(channel, tim[i], pay[i], tim[i], sequence=i)
        writer.finish()
    return time.perf_counter() - start


def read_fast(path: Path) -> tuple[float, int]:
    start = time.perf_counter()
    n = sum(len(td) for td in read_fixed_topics(path).values())
    return time.perf_counter() - start, n


def read_generic(path: Path, topics: list[str]) -> tuple[float, int]:
    start = time.perf_counter()
    with open(path, "rb") as f:
        n = sum(1 for _ in make_reader(f).iter_messages(topics=topics, log_time_order=False))
    return time.perf_counter() - start, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=1_000_000, help="messages in all (3 topics)")
    parser.add_argument(
        "--batch-ms", default="20,100,1000", help="samples per topic per write() call, ms (comma list)"
    )
    args = parser.parse_args()
    batch_ms = [float(b) for b in args.batch_ms.split(",")]
    data = build(args.messages)
    n = sum(len(rows) for _, rows in data.values())
    seconds = (max(int(t[-1]) for t, _ in data.values()) - T0) / 1e9
    per_topic = ", ".join(f"{name} {len(rows)}" for name, (_, rows) in data.items())
    print(
        f"record speed, robot vsl, {n} messages ({per_topic}), {seconds:.0f} s of session, zstd, 1 MiB chunks"
    )
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session_files = []
        t_reference = write_reference(tmp / "reference.mcap", data, list(batches(data, batch_ms[0])))
        size = (tmp / "reference.mcap").stat().st_size / 1e6
        print(
            f"  {'write mcap Writer (add_message)':<40}: {n / t_reference:11,.0f} msg/s  "
            f"({t_reference:6.2f} s, {size:.1f} MB)"
        )
        runs = [(ms, True) for ms in batch_ms] + [(batch_ms[0], False)]
        for k, (ms, standard) in enumerate(runs):
            order = list(batches(data, ms))
            t_session, path = write_session(tmp / f"session{k}", data, order, standard)
            session_files.append(path)
            size = path.stat().st_size / 1e6
            what = f"write SessionWriter, {ms:g} ms batches" + ("" if standard else ", no /tf…")
            print(
                f"  {what:<40}: {n / t_session:11,.0f} msg/s  "
                f"({t_session:6.2f} s, {size:.1f} MB, {1e6 * t_session / len(order):5.0f} us/call)  "
                f"{t_reference / t_session:5.1f}x mcap Writer, {seconds / t_session:6,.0f}x real time"
            )
        t_fast, n_fast = read_fast(session_files[0])
        t_generic, n_generic = read_generic(session_files[0], list(data))
        _, n_reference = read_fast(tmp / "reference.mcap")
    assert n_fast == n_generic == n_reference == n, (n, n_fast, n_generic, n_reference)
    print(f"  {'read read_fixed_topics':<40}: {n / t_fast:11,.0f} msg/s  ({t_fast:6.2f} s, decoded rows)")
    print(f"  {'read iter_messages (not decoded)':<40}: {n / t_generic:11,.0f} msg/s  ({t_generic:6.2f} s)")
    print(f"    {'ratio':<38}: {t_generic / t_fast:11.1f}x")


if __name__ == "__main__":
    main()
