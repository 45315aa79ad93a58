"""Builds and grids on a Dask cluster: one worker against two on this machine, the per-job costs and sizes.

    python bench/cluster.py [--sessions 128] [--points-per-session 20] [--models 16] [--epochs 20]

Simulates a campaign of ``--sessions`` sessions (not timed), then on a LocalCluster of 1 and of 2 worker
processes (one thread each) times the cold build of its dataset (every per-session stage runs: ingest, clean,
sync, segment; then registration and D) and a grid of ``--models`` networks on it (the small residual net
and the paper net × seeds, one torch thread per job). Prints the wall times, the 2-worker speed-up, the
per-job costs (worker seconds per session and per model), the data sizes (MiB per session, of the dataset,
per model) and the machine's load average before and after, then estimates 10,000 sessions and 1,000 models
on N machines from those costs (docs/how-to/scale-out.md). The estimate assumes jobs spread evenly and a
shared file system that keeps up; a session costs in proportion to its length, a model to its rows × epochs.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import yaml

from acquisition.recorder.sessions import SessionStore
from pipeline.build import build
from pipeline.cluster import cluster_executor, local_cluster
from pipeline.grid import load_grid, run_grid
from pipeline.lab import Lab
from twin.runner import simulate_experiment

PRESETS = ("small-residual", "paper")


def _mib(paths) -> float:
    return sum(p.stat().st_size for p in paths) / 2**20


def _grid(path: Path, models: int, epochs: int) -> Path:
    seeds = max(1, models // len(PRESETS))
    grid = {
        "models": [{"direction": "inverse", "preset": name} for name in PRESETS],  # their own sizes
        "datasets": ["campaign"], "splits": ["split_random"], "seeds": list(range(seeds)),
        "train": {"max_epochs": epochs, "patience": epochs, "batch_size": 64},
    }  # fmt: skip
    path.write_text(yaml.safe_dump(grid))
    return path


def run(workers: int, root: Path, sessions: list[Path], grid: Path) -> dict:
    """Cold build and grid on a fresh lab (the sessions shared) with a cluster of ``workers``."""
    lab = root / f"lab-{workers}"
    lab.mkdir()
    (lab / "sessions").symlink_to(sessions[0].parent)
    with local_cluster(workers, port=0) as cluster, cluster_executor(cluster.scheduler_address) as executor:
        start = time.perf_counter()
        report = build(sessions, Lab(lab), "campaign", executor=executor)
        build_s = time.perf_counter() - start
        start = time.perf_counter()
        results = run_grid(Lab(lab), load_grid(grid), executor=executor, threads=1)
        grid_s = time.perf_counter() - start
    train_s = sum(r["train_time_s"] for r in results)
    models = list((lab / "models").rglob("*"))
    return {"workers": workers, "build_s": build_s, "grid_s": grid_s, "rows": report.rows,
            "models": len(results), "train_s": train_s, "dataset_mib": _mib(report.path.glob("*.parquet")),
            "model_mib": _mib(p for p in models if p.is_file()) / max(1, len(results))}  # fmt: skip


def estimate(per_session_s: float, per_model_s: float, session_mib: float, model_mib: float) -> None:
    """10,000 sessions and 1,000 models on N machines of 16 workers, from the measured per-job costs."""
    print("\nestimate (jobs spread evenly, a shared file system that keeps up; 16 one-thread workers each):")
    print(f"  {'machines':>8} {'10,000 sessions':>16} {'1,000 models':>13}")
    for machines in (1, 4, 16, 64):
        workers = 16 * machines
        build_min = 10_000 * per_session_s / workers / 60
        train_min = 1_000 * per_model_s / workers / 60
        print(f"  {machines:8d} {build_min:12.1f} min {train_min:9.1f} min")
    print(f"  data: {10_000 * session_mib / 1024:.1f} GiB of sessions, {1_000 * model_mib:.0f} MiB of models")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=128)
    parser.add_argument("--points-per-session", type=int, default=20)
    parser.add_argument("--models", type=int, default=16)
    parser.add_argument("--epochs", type=int, default=20)
    args = parser.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        points = args.sessions * args.points_per_session
        simulate_experiment("campaign", SessionStore(root / "sessions"), seed=0, benches=args.sessions,
                            overrides={"points": points})  # fmt: skip
        sessions = sorted((root / "sessions").iterdir())
        session_mib = _mib(root.rglob("*.mcap")) / len(sessions)
        print(f"{len(sessions)} sessions of {args.points_per_session} settled points, {session_mib:.2f} MiB "
              f"each (simulated in {time.perf_counter() - start:.0f} s, not timed)")  # fmt: skip
        grid = _grid(root / "grid.yaml", args.models, args.epochs)
        runs = [run(workers, root, sessions, grid) for workers in (1, 2)]
    one, two = runs
    print(f"\n{'workers':>7} {'build s':>8} {'grid s':>7} {'rows':>6} {'models':>6}")
    for r in runs:
        print(f"{r['workers']:7d} {r['build_s']:8.1f} {r['grid_s']:7.1f} {r['rows']:6d} {r['models']:6d}")
    print(f"2 workers against 1: build ×{one['build_s'] / two['build_s']:.2f}, "
          f"grid ×{one['grid_s'] / two['grid_s']:.2f} (2 cores: ×2 at best)")  # fmt: skip
    per_session_s = one["build_s"] / len(sessions)  # one worker: its wall time is the jobs' own
    per_model_s = one["grid_s"] / one["models"]
    print(f"per job (1 worker): {per_session_s:.2f} s per session (build), {per_model_s:.1f} s per model "
          f"({args.epochs} epochs, {one['rows']} rows); dataset {one['dataset_mib']:.2f} MiB, "
          f"{one['model_mib']:.2f} MiB per model")  # fmt: skip
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    estimate(per_session_s, per_model_s, session_mib, one["model_mib"])


if __name__ == "__main__":
    main()
