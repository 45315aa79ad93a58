"""What the history-aware hybrid's history is worth in the loop: Experiment 2 on the twin with its unmodelled
effects (vsl_unmodelled), commanded by the history-aware hybrid and by the same regressor without the history,
both trained on the same rows (Experiment 1 on that twin, every cell but the two Experiment 2 follows, at each
set-point's end: ``pipeline.unmodelled.path_rows``), beside the model-based IK.

    python bench/history_in_loop.py [--lab DIR] [--points N]

Prints the mean and p95 distance to the desired curve (mm) per case and command, and the machine's load.
About a minute on 2 cores (a 600-point campaign for the tracker's registration, Experiment 1 with two
repetitions, Experiment 2 twice); ``--lab`` keeps what it made (a second run reuses the sessions).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from pipeline.lab import Lab


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--lab", type=Path, default=None, help="where to keep the sessions (default: a temp dir)"
    )
    parser.add_argument("--points", type=int, default=600, help="campaign points (the registration's)")
    args = parser.parse_args(argv)

    from analysis.vsl_paths import path_errors
    from pipeline import unmodelled
    from pipeline.baselines import SklearnBaseline
    from pipeline.history import PATHS, HistoryModel
    from pipeline.simulated import simulated_datasets

    start, load_before = time.perf_counter(), os.getloadavg()
    with tempfile.TemporaryDirectory() as scratch:
        study = Lab(args.lab or Path(scratch)).study("unmodelled")
        experiments = unmodelled.study_experiments(study, args.points, unmodelled.STUDY["paths"])
        drawn_campaign, _, on_paths = experiments
        drawn = drawn_campaign.lab
        campaign, paths = simulated_datasets(study, [drawn_campaign, on_paths])  # not the shuffled one
        rows = unmodelled.path_rows(drawn, paths.version)
        models = {
            "history-aware hybrid": HistoryModel("inverse", PATHS).fit(rows),
            "without the history": SklearnBaseline("gbr", "inverse").fit(rows),
        }
        errors = {}
        for k, (label, model) in enumerate(models.items()):
            commands = ["ik", "history"] if k == 0 else ["history"]
            table = unmodelled.experiment2_rows(
                drawn,
                study.study(f"experiment2-{k}").sessions,
                f"experiment2-{k}",
                0,
                campaign.version,
                commands,
                {"history": model},
                {"history": f"{label} on the paths of campaign@{campaign.version}"},
            )
            table = path_errors(table)
            for row in table.itertuples():
                name = "model-based IK" if row.mode == "ik" else label
                errors[(name, f"{row.payload_g:g} g at {row.pressure_bar:g} bar")] = (row.mean_mm, row.p95_mm)
    cases = sorted({case for _, case in errors})
    print(
        f"Experiment 2 on vsl_unmodelled, {len(rows)} training rows; distance to the curve, mean / p95 (mm):"
    )
    print(f"| command | {' | '.join(cases)} |")
    print("|---|" + "---|" * len(cases))
    for name in dict.fromkeys(n for n, _ in errors):
        cells = [f"{errors[name, c][0]:.3f} / {errors[name, c][1]:.3f}" for c in cases]
        print(f"| {name} | {' | '.join(cells)} |")
    print(f"{time.perf_counter() - start:.0f} s; {os.cpu_count()} cores, load average {load_before[0]:.2f} "
          f"before, {os.getloadavg()[0]:.2f} after")  # fmt: skip


if __name__ == "__main__":
    main()
