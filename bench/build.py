"""End-to-end dataset build: the paper-size campaign (17,568 static points) from MCAP sessions to D.

Simulates the campaign on the twin (not timed: see bench/simulate.py), then times `vslab build`'s work:
cold (every stage runs: ingest, clean, sync, segment per session in parallel processes; registration, D,
splits), warm (nothing changed: the version is found, no stage runs) and with one parameter changed (the
per-session stages come from the cache). Prints rows, failed settled windows and the times.
Usage: python bench/build.py [--points N] [--benches B] [--workers W]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import tempfile
import time
from pathlib import Path

from acquisition.recorder.sessions import SessionStore
from pipeline.build import build
from pipeline.lab import Lab
from twin.runner import simulate_experiment


def end_to_end(points: int, benches: int, workers: int) -> None:
    """Simulate the campaign, then time the cold, warm and re-parameterised builds."""
    with tempfile.TemporaryDirectory() as tmp:
        lab = Path(tmp)
        start = time.perf_counter()
        simulate_experiment(
            "campaign", SessionStore(lab / "sessions"), benches=benches, overrides={"points": points}
        )
        sessions = sorted((lab / "sessions").iterdir())
        size = sum(p.stat().st_size for p in lab.rglob("*.mcap")) / 2**20
        print(f"end to end: campaign of {points:,} points in {len(sessions)} sessions, {size:.0f} MiB "
              f"(simulated in {time.perf_counter() - start:.1f} s, not counted)")  # fmt: skip
        for label, params in (("cold", {}), ("warm", {}), ("new split seed", {"splits": {"seed": 1}})):
            with cf.ProcessPoolExecutor(workers) as pool:
                start = time.perf_counter()
                report = build(sessions, Lab(lab), "campaign", params, executor=pool)
                wall = time.perf_counter() - start
            print(f"  build {label:<15} {wall:7.1f} s  {report.rows:6,d} rows  built={report.built!s:<5}  "
                  f"cached {report.cached}/{len(sessions)}  failed {len(report.failed)}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=17568, help="campaign size (the paper's n = 17568)")
    parser.add_argument("--benches", type=int, default=128, help="sessions (twin benches)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="build processes")
    args = parser.parse_args()
    end_to_end(args.points, args.benches, args.workers)


if __name__ == "__main__":
    main()
