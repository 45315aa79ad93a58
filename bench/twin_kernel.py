"""Twin speed: simulated seconds per wall second, one robot and a batch of 256 (after compilation).

Targets (issue 2): ≥ 50× real time for one robot on one core, ≥ 2000× aggregate for a batch of 256.
The physics runs at 1 kHz; robots of a batch run in parallel threads (numba prange) on the machine's cores.
Usage: python bench/twin_kernel.py [--seconds S] [--robot vsl|popup|vsl_rigid]
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

from models.robot import load_robot
from twin.world import World


def speed(robot_name: str, batch: int, seconds: float, threads: int, repeats: int = 3) -> float:
    """Best-of-``repeats`` simulated seconds per wall second, summed over the batch."""
    numba.set_num_threads(threads)
    robot = load_robot(robot_name)
    q0 = np.deg2rad([0, 60, -120]) if robot_name == "popup" else np.deg2rad([0, 30, -60])
    world = World(robot, batch=batch, seed=0, q0=q0, payload_kg=0.05)
    world.step(1)  # compile (cached on disk after the first run)
    rng = np.random.default_rng(0)
    best = np.inf
    for _ in range(repeats):
        # keep the arm moving so the loop does real work: a new random goal every 0.5 s
        start = time.perf_counter()
        for _ in range(max(1, round(seconds / 0.5))):
            world.command_joints(q0 + rng.uniform(-0.3, 0.3, size=(batch, 3)))
            world.run_for(0.5)
        best = min(best, time.perf_counter() - start)
    return batch * seconds / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per measurement")
    parser.add_argument("--robot", default="vsl")
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    single = speed(args.robot, 1, args.seconds * 4, threads=1)
    batch = speed(args.robot, 256, args.seconds, threads=cores)
    print(f"twin speed, robot {args.robot}, 1 kHz physics, {cores} cores")
    print(f"  1 robot, 1 thread     : {single:8.0f}x real time   (target >= 50x)")
    print(f"  256 robots, {cores} threads : {batch:8.0f}x real time aggregate   (target >= 2000x)")


if __name__ == "__main__":
    main()
