"""A lab on an S3 endpoint against the same lab in a local folder: uploads, cold builds and a grid.

    python bench/lab_store.py [--sessions 32] [--points-per-session 20] [--models 4] [--epochs 10]

Starts moto's S3 server in a process of its own on 127.0.0.1 (an emulator: the network is loopback, the
store is moto's memory, so this measures vslab's own cost of going through fsspec and S3's requests, not a
real store's latency or bandwidth), simulates a campaign into a local lab (not timed), then times:
- the upload of its sessions to the store (`sessions upload`: parts first, session.json last);
- a cold build of the campaign from each lab (every per-session stage runs, 2 worker processes);
- a grid of ``--models`` networks on each (2 worker processes, one torch thread each).
Prints the times, the ratio store / local, the requests the store answered (from moto's own log), the data
sizes and the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from acquisition.recorder.sessions import SessionStore
from pipeline.lab import Lab


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mib(paths) -> float:
    return sum(p.stat().st_size for p in paths if p.is_file()) / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=32)
    parser.add_argument("--points-per-session", type=int, default=20)
    parser.add_argument("--models", type=int, default=4)
    parser.add_argument("--epochs", type=int, default=10)
    args = parser.parse_args()

    port = _free_port()
    env = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"}  # fmt: skip
    os.environ.update(env)  # before s3fs and the worker processes read them
    log = tempfile.NamedTemporaryFile("w+", prefix="moto-", suffix=".log")
    server = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=log)  # fmt: skip
    try:
        _bench(args, lambda: Path(log.name).read_text().count(" HTTP/1.1"))  # moto logs each request
    finally:
        server.terminate()
        server.wait(10)
        log.close()


def _bench(args, requests) -> None:
    """``requests()``: how many requests the store has answered so far."""
    import s3fs

    from acquisition.recorder.sessions import publish_session
    from acquisition.storage import lab_path
    from pipeline.build import build
    from pipeline.grid import load_grid, run_grid
    from twin.runner import simulate_experiment

    fs = s3fs.S3FileSystem()
    for _ in range(100):  # the server is up once it answers
        try:
            fs.mkdir("bench")
            break
        except Exception:  # connection refused while it starts
            time.sleep(0.1)
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "lab"
        points = args.sessions * args.points_per_session
        simulate_experiment("campaign", SessionStore(local / "sessions"), seed=0, benches=args.sessions,
                            overrides={"points": points})  # fmt: skip
        sessions = sorted((local / "sessions").iterdir())
        store = lab_path("s3://bench/lab")
        start = time.perf_counter()
        for s in sessions:
            publish_session(s, store / "sessions")
        upload_s = time.perf_counter() - start
        remote_sessions = sorted((store / "sessions").iterdir())
        grid_file = Path(tmp) / "grid.yaml"
        presets = ("small-residual", "paper")
        grid_file.write_text(yaml.safe_dump({
            "models": [{"direction": "inverse", "preset": p} for p in presets], "datasets": ["campaign"],
            "splits": ["split_random"], "seeds": list(range(max(1, args.models // len(presets)))),
            "train": {"max_epochs": args.epochs, "patience": args.epochs, "batch_size": 64},
        }))  # fmt: skip
        times, counts = {}, {}
        for name, lab, found in (("local", local, sessions), ("s3", store, remote_sessions)):
            start, before = time.perf_counter(), requests()
            report = build(found, Lab(lab), "campaign")
            times[name, "build"] = time.perf_counter() - start
            counts[name, "build"] = requests() - before
            start, before = time.perf_counter(), requests()
            results = run_grid(Lab(lab), load_grid(grid_file), workers=2, threads=1)
            times[name, "grid"] = time.perf_counter() - start
            counts[name, "grid"] = requests() - before
            times[name, "version"] = report.version
            times[name, "models"] = sorted(r["version"] for r in results)
        mib = _mib(p for s in sessions for p in s.iterdir())
    load_after = os.getloadavg()
    assert times["local", "version"] == times["s3", "version"], "the store's dataset is not the local one"
    assert times["local", "models"] == times["s3", "models"], "the store's model versions differ"
    print(f"cores {os.cpu_count()}; load average before {load_before[0]:.1f}, after {load_after[0]:.1f}")
    print(f"{len(sessions)} sessions, {mib:.1f} MiB; upload to the store {upload_s:.1f} s "
          f"({mib / upload_s:.1f} MiB/s)")  # fmt: skip
    print(f"{'':8}{'local':>10}{'s3':>10}{'s3/local':>10}{'requests':>10}")
    for step in ("build", "grid"):
        lo, s3 = times["local", step], times["s3", step]
        print(f"{step:8}{lo:>9.1f}s{s3:>9.1f}s{s3 / lo:>9.2f}×{counts['s3', step]:>10}")
    print(f"dataset {times['local', 'version']} and {len(times['local', 'models'])} model versions: the same")


if __name__ == "__main__":
    main()
