"""Ingest speed: ``pipeline.ingest.ingest_session`` (chunk-speed fast path into DataFrames) against the
generic mcap-ros2-support reader decoding the same files.

Targets: the fast path ≥ 1 M messages/s end to end (MCAP parts → one pandas DataFrame per topic, events and
the sha256 of the parts included), and ≥ 10× the generic reader. The generic figure is
``make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()`` over the same parts, messages
only (no table built: flattering to it); it decodes sessions until ``--generic-s`` seconds have passed and the
rate is extrapolated to the whole set (the output says when). The sessions are a campaign simulated into a
temporary directory first (not timed); ``clean`` is timed too, for reference. Then the end-to-end time to
build the dataset of a paper-size campaign (17,568 points; bench/build.py, skip with --no-build).
Usage: python bench/ingest.py [--points N] [--benches B] [--generic-s S] [--no-build]
"""

from __future__ import annotations

import argparse
import os
import runpy
import tempfile
import time
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from acquisition.recorder.sessions import SessionStore
from acquisition.schemas.session_card import readable_parts
from pipeline.clean import clean
from pipeline.ingest import ingest_session
from twin.runner import simulate_experiment

TARGET_MSG_S = 1e6
TARGET_RATIO = 10.0


def fast_path(sessions: list[Path]) -> tuple[int, float, float]:
    """(messages, ingest seconds, clean seconds) over every session."""
    messages, ingest_s, clean_s = 0, 0.0, 0.0
    for directory in sessions:
        start = time.perf_counter()
        tables = ingest_session(directory)
        ingest_s += time.perf_counter() - start
        messages += sum(len(df) for df in tables.streams.values()) + len(tables.events)
        start = time.perf_counter()
        clean(tables)
        clean_s += time.perf_counter() - start
    return messages, ingest_s, clean_s


def generic_path(sessions: list[Path], budget_s: float) -> tuple[int, float, int]:
    """(messages, seconds, sessions decoded) with mcap-ros2-support, stopping after ``budget_s``."""
    messages, elapsed, done = 0, 0.0, 0
    for directory in sessions:
        if elapsed >= budget_s:
            break
        start = time.perf_counter()
        for part in readable_parts(directory):
            with open(part, "rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                for _ in reader.iter_decoded_messages(log_time_order=False):
                    messages += 1
        elapsed += time.perf_counter() - start
        done += 1
    return messages, elapsed, done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1600, help="campaign points (≈1,300 messages each)")
    parser.add_argument("--benches", type=int, default=32, help="twin benches = sessions")
    parser.add_argument("--generic-s", type=float, default=30.0, help="time budget of the generic reader")
    parser.add_argument("--no-build", action="store_true", help="skip the end-to-end campaign build")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sessions"
        start = time.perf_counter()
        reports = simulate_experiment(
            "campaign", SessionStore(root), benches=args.benches, overrides={"points": args.points}
        )
        written = sum(r.messages for r in reports)
        sessions = sorted(d for d in root.iterdir() if d.is_dir())
        size = sum(p.stat().st_size for p in root.rglob("*.mcap")) / 2**20
        sim_s = time.perf_counter() - start
        print(
            f"campaign: {args.points} points on {args.benches} benches → {len(sessions)} sessions, "
            f"{written:,d} messages, {size:.0f} MiB (simulated in {sim_s:.1f} s)"
        )
        fast_path(sessions[:1])  # warm-up: imports, page cache
        n_fast, ingest_s, clean_s = fast_path(sessions)
        n_generic, generic_s, done = generic_path(sessions, args.generic_s)
    fast_rate, generic_rate = n_fast / ingest_s, n_generic / generic_s
    verdict = "ok" if fast_rate >= TARGET_MSG_S else "MISSED"
    ratio = fast_rate / generic_rate
    print(f"  fast path   ingest_session   {n_fast:12,d} msgs {ingest_s:8.2f} s {fast_rate:12,.0f} msg/s  "
          f"({verdict}, ≥ {TARGET_MSG_S:,.0f})")  # fmt: skip
    extrapolated = done < len(sessions)
    note = f"  (timed {done}/{len(sessions)} sessions, extrapolated: ≈{n_fast / generic_rate:,.0f} s for all)"
    print(
        f"  generic     mcap_ros2 decode {n_generic:12,d} msgs {generic_s:8.2f} s {generic_rate:12,.0f} msg/s"
        + (note if extrapolated else "")
    )
    print(
        f"  ratio       {ratio:6.1f}×  ({'ok' if ratio >= TARGET_RATIO else 'MISSED'}, ≥ {TARGET_RATIO:.0f}×)"
    )
    print(
        f"  clean       (reference)      {n_fast:12,d} msgs {clean_s:8.2f} s {n_fast / clean_s:12,.0f} msg/s"
    )
    if not args.no_build:
        runpy.run_path(str(Path(__file__).with_name("build.py")))["end_to_end"](
            17568, 128, os.cpu_count() or 1
        )


if __name__ == "__main__":
    main()
