"""Simulated-time runner speed: the full Experiment 1 and the paper-size campaign on the batched twin.

Targets (issue 4): Experiment 1 (3 trajectories × 5 payloads × 5 arms × 5 repetitions = 375 runs) and the
17,568-point campaign each in under 5 minutes on this machine, written as sessions (MCAP), as `vslab simulate`
does (the benches spread over every core). Also Experiment 2 (model-based and static-compensated commands;
the hybrid ones need a trained model) and the POPUP link tests. Prints wall time, bench-seconds simulated, the
speed-up over real time and the messages written; every plan is safety-checked before it runs and while it
runs.
Usage: python bench/simulate.py [--points N] [--benches B] [--only PROTOCOL]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from acquisition.recorder.sessions import SessionStore
from twin.runner import simulate_experiment

TARGET_S = 300.0
GROUPS = {  # what --only picks → the experiments it runs
    "experiment1": ("experiment1",),
    "campaign": ("campaign",),
    "experiment2": ("experiment2",),
    "popup": ("popup_static", "popup_impact", "popup_deploy"),
}


def run(protocol: str, benches: int, overrides: dict) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        reports = simulate_experiment(protocol, SessionStore(Path(tmp) / "sessions"), benches=benches,
                                      overrides=overrides, processes=os.cpu_count() or 1)  # fmt: skip
        wall = time.perf_counter() - start
        sessions = sum(len(r.sessions) for r in reports)
        simulated = sum(r.simulated_s for r in reports)
        messages = sum(r.messages for r in reports)
        size = sum(p.stat().st_size for p in Path(tmp).rglob("*.mcap")) / 2**20
    verdict = "ok" if wall < TARGET_S else "MISSED"
    print(
        f"  {protocol:<12} {wall:7.1f} s wall ({verdict}, < {TARGET_S:.0f} s)  {sessions:4d} sessions  "
        f"{simulated:9,.0f} bench-s  {simulated / wall:6.0f}× real time  {messages:12,d} messages  "
        f"{messages / wall:9,.0f} msg/s  {size:6.0f} MiB"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=GROUPS, help="one group of experiments (default: all)")
    parser.add_argument("--points", type=int, default=17568, help="campaign size (the paper's n = 17568)")
    parser.add_argument("--benches", type=int, default=128, help="twin benches stepped together")
    args = parser.parse_args()
    overrides = {"campaign": {"points": args.points}, "experiment2": {"commands": ["ik", "static"]}}
    print("simulated-time runner (numba twin, sessions written to MCAP)")
    for group, experiments in GROUPS.items():
        if args.only in (None, group):
            for experiment in experiments:
                run(experiment, args.benches, overrides.get(experiment, {}))


if __name__ == "__main__":
    main()
