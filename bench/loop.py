"""The lab's loop, figure by figure, beside its goal (issue 32), with the machine's load average.

    python bench/loop.py [--only main,second,campaign,ingest,build,check,test] [--points N] [--benches B]
                         [--profile]

- main: `vslab demo` (the main job, what `make demo` runs) on a new lab, wall seconds, its steps, and its
  physical floor: the arithmetic of the networks it trained (from their cards) at this machine's measured
  float32 matmul rate; second: the same command again on that lab (goal: nothing recomputed that has not
  changed).
- campaign: the paper-size campaign (17,568 points on 128 benches, spread over the cores as `vslab simulate`
  does) simulated into MCAP sessions.
- ingest: ``pipeline.ingest.ingest_session`` over those sessions (messages per second, page cache warm).
- build: the cold build of that campaign into its dataset (every stage, both cores).
- check / test: `make check` and `make test` on a fresh clone of this repository (the clone's own virtual
  environment included in `make test`'s time, as CI pays it); `make check` runs after, in that clone.

Each figure is printed as it is measured, then a table of all with their goals. Exit status 1 if a measured
figure misses its goal. ``--profile``: the campaign, ingest and build also run under cProfile (timed apart
from the figures) and the functions that took the most time are printed: where each step's time goes.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import os
import runpy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# figure → (goal, unit, higher is better)
GOALS = {
    "main": (240.0, "s", False),
    "second": (20.0, "s", False),
    "campaign": (20.0, "s", False),
    "build": (10.0, "s", False),
    "ingest": (3e6, "msg/s", True),
    "test": (600.0, "s", False),
    "check": (120.0, "s", False),
}
WHAT = {
    "main": "main job, `vslab demo`",
    "second": "a second `vslab demo`, same lab",
    "campaign": "campaign simulated (17,568 points)",
    "ingest": "ingest fast path",
    "build": "cold build of that campaign",
    "test": "fresh-clone `make test`, in all",
    "check": "`make check` (the fast tier)",
}


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} {five:.2f} {fifteen:.2f}"


def python_yardstick(n: int = 10_000_000) -> float:
    """Seconds one core takes for ``n`` additions in a plain Python loop: how fast this machine runs the
    Python the loop's figures spend most of their time in (the goals were set on one machine; the same
    code measured on a slower one reads slower by about this ratio)."""
    start, total = time.perf_counter(), 0
    for i in range(n):
        total += i
    return time.perf_counter() - start


def _timed(cmd: list[str], cwd: Path, log: Path) -> float:
    """Wall seconds of ``cmd``, its output in ``log``; raises if it fails. Also prints the CPU seconds the
    machine's cores were busy meanwhile, and what that alone costs on them run side by side (the figure's
    floor, however the work were scheduled). Counted from /proc/stat, so every process is in it (workers of
    a forkserver are not the command's children to be accounted), and so is whatever else ran: the load
    average beside each figure says how much that was."""
    busy_before = _busy_cpu_s()
    start = time.perf_counter()
    with open(log, "w") as out:
        code = subprocess.call(cmd, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
    if code:
        raise SystemExit(f"{' '.join(cmd)} failed with {code}: see {log}")
    wall = time.perf_counter() - start
    if (busy := _busy_cpu_s()) is not None and busy_before is not None:
        cpu, cores, name = busy - busy_before, os.cpu_count() or 1, " ".join(Path(c).name for c in cmd)
        print(
            f"  `{name}`: the cores busy {cpu:.0f} CPU-seconds meanwhile (user + system, every process) "
            f"≥ {cpu / cores:.0f} s on {cores} cores; {cpu / wall:.2f} cores busy on average",
            flush=True,
        )
    return wall


def _cpu_s() -> list[float] | None:
    """The seconds of /proc/stat's first line since boot, every core together (user, nice, system, idle,
    iowait, irq, softirq, steal, ...); None where there is none to read."""
    try:
        with open("/proc/stat") as f:
            return [int(v) / os.sysconf("SC_CLK_TCK") for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None


def _busy_cpu_s() -> float | None:
    """Seconds every core of this machine has spent busy since boot (all but idle, iowait and the time the
    hypervisor took); None where there is no /proc/stat."""
    if (cpu := _cpu_s()) is None:
        return None
    user, nice, system, _idle, _iowait, irq, softirq = cpu[:7]
    return user + nice + system + irq + softirq


def _stolen_s() -> float:
    """Seconds of this machine's CPU the hypervisor has taken since boot (0 where none is counted)."""
    cpu = _cpu_s()
    return cpu[7] if cpu is not None and len(cpu) > 7 else 0.0


def main_job(tmp: Path, figures: dict, only: set[str]) -> None:
    lab = tmp / "lab"
    cmd = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "demo"]
    figures["main"] = _timed(cmd, ROOT, tmp / "main.log")  # a second run needs a first
    _report("main", figures)
    steps = json.loads((lab / "report" / "timings.json").read_text())  # where the main job's time went
    print("  " + ", ".join(f"{step} {s:.1f} s" for step, s in steps.items()), flush=True)
    flops, nets = training_flops(lab)
    rate = matmul_rate()
    floor = flops / rate
    print(f"  its {nets} networks' training arithmetic: {flops / 1e12:.1f} Tflop ≥ {floor:.0f} s at this "
          f"machine's {rate / 1e9:.0f} Gflop/s (float32 matmul on every core, measured); the goal leaves "
          f"{GOALS['main'][0] - floor:.0f} s for everything else", flush=True)  # fmt: skip
    if "second" in only:
        figures["second"] = _timed(cmd, ROOT, tmp / "second.log")
        _report("second", figures)


def training_flops(lab: Path) -> tuple[float, int]:
    """(floating-point operations, networks) of the training of every network saved in ``lab`` (its studies'
    included), from their cards: per epoch run, 6 per weight per training row (forward 2, backward 4) and 2
    per weight per validation row. A lower bound: activations, the optimiser and Python are left out."""
    from pipeline.grid import net_weights
    from pipeline.train import TrainConfig

    total, nets = 0.0, 0
    for path in lab.glob("**/models/*/*/card.json"):
        card = json.loads(path.read_text())
        if "train_config" not in card:
            continue
        weights = net_weights(TrainConfig.from_dict(card["train_config"]).net)
        total += len(card["curves"]) * (6 * card["n_train"] + 2 * card["n_val"]) * weights
        nets += 1
    return total, nets


def matmul_rate(seconds: float = 1.0) -> float:
    """This machine's float32 matrix-multiply rate on every core (flop/s): 1024² products for ``seconds``."""
    import torch

    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    torch.mm(a, b)
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        torch.mm(a, b)
        done += 1
    return done * 2 * 1024**3 / (time.perf_counter() - start)


def profiled(what: str, step) -> None:
    """Run ``step()`` under cProfile and print the functions that took the most time, inside and in all."""
    import cProfile
    import pstats

    profile = cProfile.Profile()
    profile.runcall(step)
    print(f"\n--- cProfile of {what} (a second run, not the figure's) ---", flush=True)
    for order in ("tottime", "cumulative"):
        pstats.Stats(profile).strip_dirs().sort_stats(order).print_stats(12)


def campaign(tmp: Path, figures: dict, only: set[str], points: int, benches: int,
             profile: bool = False) -> None:  # fmt: skip
    from acquisition.recorder.sessions import SessionStore
    from pipeline.build import InlineExecutor, build
    from pipeline.lab import Lab
    from twin.runner import simulate_experiment

    lab = tmp / "campaign"
    start = time.perf_counter()
    simulate_experiment("campaign", SessionStore(lab / "sessions"), benches=benches,
                        overrides={"points": points}, processes=os.cpu_count() or 1)  # fmt: skip
    figures["campaign"] = time.perf_counter() - start
    _report("campaign", figures)
    _kernel_floor(points, benches)
    again = SessionStore(tmp / "profiled" / "sessions")
    if profile:
        profiled("the campaign", lambda: simulate_experiment("campaign", again, benches=benches,
                                                             overrides={"points": points}))  # fmt: skip
    sessions = sorted(d for d in (lab / "sessions").iterdir() if d.is_dir())
    fast_path = runpy.run_path(str(ROOT / "bench" / "ingest.py"))["fast_path"]
    if "ingest" in only:  # bench/ingest.py's measure: ingest_session timed alone, session by session
        messages, ingest_s, _ = fast_path(sessions)
        figures["ingest"] = messages / ingest_s
        _report("ingest", figures)
        if profile:
            profiled("the ingest", lambda: fast_path(sessions))
    if "build" in only:
        with cf.ProcessPoolExecutor(os.cpu_count() or 1) as pool:
            start = time.perf_counter()
            build(sessions, Lab(lab), "campaign", {}, executor=pool)
            figures["build"] = time.perf_counter() - start
        _report("build", figures)
        if profile:  # one process: the workers' stages are where the build's time goes
            inline, other = InlineExecutor(), Lab(tmp / "profiled")
            profiled(
                "the build, in one process", lambda: build(sessions, other, "campaign", {}, executor=inline)
            )


def _kernel_floor(points: int, benches: int) -> None:
    """The campaign's physical floor here: its robot-seconds stepped by the twin's kernel alone (1 kHz, one
    robot on one thread, ``bench/twin_kernel.py``'s measure) on every core, with nothing written."""
    from acquisition.plans.experiments import expand_experiment

    _, plans, _ = expand_experiment("campaign", {"points": points}, benches=benches)
    robot_s = sum(plan.duration_s for plan in plans)
    cores = os.cpu_count() or 1
    per_core = runpy.run_path(str(ROOT / "bench" / "twin_kernel.py"))["speed"]("vsl", 1, 20.0, threads=1)
    floor = robot_s / per_core / cores
    print(f"  its floor: {robot_s:,.0f} robot-seconds at {per_core:,.0f}× real time a core (the kernel "
          f"alone, one robot a thread) on {cores} cores = {floor:.1f} s of physics; the rest is the "
          "sensors, the clocks, the session files and zstd", flush=True)  # fmt: skip


def suite(tmp: Path, figures: dict, only: set[str]) -> None:
    """`make test`, then `make check`, on a fresh clone with ../shared beside it (as CI has it)."""
    clone = tmp / "ci" / "main"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    (tmp / "ci" / "shared").symlink_to(ROOT.parent / "shared")
    if "test" in only:
        figures["test"] = _timed(["make", "test"], clone, tmp / "test.log")
        _report("test", figures)
    if "check" in only:
        if "test" not in only:
            _timed(["make", ".venv/bin/.installed"], clone, tmp / "install.log")
        figures["check"] = _timed(["make", "check"], clone, tmp / "check.log")
        _report("check", figures)


def _verdict(name: str, value: float) -> tuple[str, bool]:
    goal, unit, higher = GOALS[name]
    ok = value >= goal if higher else value <= goal
    shown = f"{value / 1e6:.2f} M {unit}" if unit == "msg/s" else f"{value:.1f} {unit}"
    target = f"≥ {goal / 1e6:.0f} M {unit}" if unit == "msg/s" else f"≤ {goal:.0f} {unit}"
    return f"{WHAT[name]:<38} {shown:>14}   goal {target:<12} {'ok' if ok else 'MISSED'}", ok


def _report(name: str, figures: dict) -> None:
    print(_verdict(name, figures[name])[0] + f"   (load {_load()})", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(GOALS), help="comma-separated figures (default: all)")
    parser.add_argument("--points", type=int, default=17568, help="campaign points (the paper's n = 17568)")
    parser.add_argument("--benches", type=int, default=128, help="campaign sessions (twin benches)")
    parser.add_argument("--profile", action="store_true", help="also profile the campaign, ingest and build")
    args = parser.parse_args()
    only = {name.strip() for name in args.only.split(",") if name.strip()}
    if unknown := only - set(GOALS):
        parser.error(f"unknown figure(s) {sorted(unknown)}: choose from {', '.join(GOALS)}")
    WHAT["campaign"] = f"campaign simulated ({args.points:,} points)"
    yardstick = python_yardstick()
    print(f"bench/loop.py on {os.cpu_count()} cores, load average at the start {_load()}; this machine's "
          f"yardstick: 10 M Python additions in {yardstick:.2f} s on one core", flush=True)  # fmt: skip
    stolen_at_start = _stolen_s()
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="loop-") as name:
        tmp = Path(name)
        if only & {"campaign", "ingest", "build"}:
            campaign(tmp, figures, only, args.points, args.benches, args.profile)
        if only & {"main", "second"}:
            main_job(tmp, figures, only)
        if only & {"test", "check"}:
            suite(tmp, figures, only)
    print(f"\nfigure{'':<33} {'measured':>14}   goal             (load average at the end {_load()}; "
          f"{_stolen_s() - stolen_at_start:.1f} CPU-seconds taken by the hypervisor meanwhile)")  # fmt: skip
    missed = False
    for name in GOALS:
        if name in figures:
            line, ok = _verdict(name, figures[name])
            missed |= not ok
            print(line)
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
