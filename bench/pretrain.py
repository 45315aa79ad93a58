"""Pretraining on the lab's twin (issue 33): does a net pretrained on the fitted twin's campaign and
fine-tuned on 10 % of a lab's measured rows do as well as the net trained on all of them alone?

A lab's arm the twin is not told about (``bench/lab_arm.yaml``: links ×0.8 and ×1.25, lengths ±2 mm) records
a campaign (the measured rows). With 10 % of its train and val sessions (``split_group`` deals whole
sessions, so no test row is ever seen), the twin is fitted (``vslab twin fit``), its campaign simulated
(``twin-<name>``), a net pretrained on it; then at 1, 2, 5, 10, 20, 50 and 100 % of the measured train and val
sessions the same net is trained alone and fine-tuned from the pretrained weights, each scored on the whole
test part. Prints the curve (the twin saw the 10 % sessions: at 1–5 % it saw more than the nets), the verdict
at 10 %, the rows each used, the time and the machine's load; ``--out DIR`` also draws the curve.

    python bench/pretrain.py [--points 17568] [--twin-points 17568] [--preset small-residual] [--lab DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LAB_ARM = ROOT / "bench" / "lab_arm.yaml"


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--points", type=int, default=17568, help="the lab's measured campaign (paper: 17568)"
    )
    parser.add_argument("--twin-points", type=int, default=17568, help="the fitted twin's campaign")
    parser.add_argument("--benches", type=int, default=128, help="sessions of the measured campaign")
    parser.add_argument("--direction", default="inverse", choices=("inverse", "forward"))
    parser.add_argument("--preset", default="small-residual", help="a preset of models.hybrid")
    parser.add_argument("--max-epochs", type=int, default=300)
    parser.add_argument(
        "--lab", type=Path, default=None, help="keep the lab here (default: a scratch folder)"
    )
    parser.add_argument("--out", type=Path, default=None, help="draw the curve into this folder")
    args = parser.parse_args()

    import yaml

    from acquisition.code_version import code_version
    from models.hybrid import preset
    from pipeline.build import build
    from pipeline.dataset_store import DatasetError
    from pipeline.lab import Lab
    from pipeline.pretrain import curve_verdict, learning_curve, measured_subset, twin_campaign
    from pipeline.train import TrainConfig
    from pipeline.twin_fit import VslStaticFit
    from twin.runner import simulate_experiment

    print(f"bench/pretrain.py on {os.cpu_count()} cores, load average at the start {_load()}", flush=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="pretrain-") as scratch:
        lab = Lab.open(args.lab or Path(scratch) / "lab")
        try:
            measured, _ = lab.datasets.load("campaign")
        except DatasetError:
            simulate_experiment("campaign", lab.sessions, seed=1, benches=args.benches,
                                overrides={"points": args.points, "robot": str(LAB_ARM)})  # fmt: skip
            report = build(sorted(Path(str(lab.sessions.root)).iterdir()), lab, "campaign")
            measured, _ = lab.datasets.load("campaign", report.version)
        print(f"the lab's campaign: {len(measured):,} rows of {measured['session'].nunique()} sessions "
              f"({time.perf_counter() - start:.0f} s)", flush=True)  # fmt: skip

        config = TrainConfig(net=preset(args.direction, args.preset), split="split_group",
                             max_epochs=args.max_epochs)  # fmt: skip
        tenth = measured_subset(measured, 0.1, config.split, config.seed)
        seen = tenth[tenth[config.split] != "test"]
        fit = VslStaticFit("vsl").fit(seen)
        fitted = Path(str(lab.twin.fitted("vsl")))
        fitted.parent.mkdir(parents=True, exist_ok=True)
        description = fit.description("vsl_fitted", "vsl", "campaign (10 % of its sessions)",
                                      code_version("pipeline.twin_fit"))  # fmt: skip
        fitted.write_text(yaml.safe_dump(description, sort_keys=False))
        print(f"twin fitted on {len(seen):,} rows of {seen['session'].nunique()} sessions: tip residual "
              f"{fit.residual_rms_mm_:.3f} mm per axis", flush=True)  # fmt: skip

        t0 = time.perf_counter()
        report = twin_campaign(lab, str(fitted), points=args.twin_points)
        twin, _ = lab.datasets.load(report.name, report.version)
        print(f"the twin's campaign: {len(twin):,} rows ({time.perf_counter() - t0:.0f} s)", flush=True)

        t0 = time.perf_counter()
        curve = learning_curve(measured, twin, config, robot=str(fitted),
                               progress=lambda text: print(f"  {text}", flush=True))  # fmt: skip
        trained = time.perf_counter() - t0
        if args.out is not None:
            from analysis.twin_report import pretraining_curve

            png = pretraining_curve(curve, args.out, made_from={"measured": "campaign", "twin": report.name})
            print(f"drawn: {png['png']}")
    shown = curve.assign(fraction=[f"{f:.0%}" if f else "twin only" for f in curve["fraction"]])
    print()
    print(shown.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    verdict = curve_verdict(curve)
    ok = verdict["ratio"] <= 1.0
    print(f"\n{args.direction}-{args.preset}, test tip error (mm, the rigid FK of the joints): pretrained on "
          f"the twin and fine-tuned on 10 % of the measured rows ({verdict['rows']:,}): "
          f"{verdict['fine_tuned']:.3f}; trained alone on all {verdict['all_rows']:,}: "
          f"{verdict['all_measured']:.3f}; ratio {verdict['ratio']:.2f} (≤ 1 asked) "
          f"{'ok' if ok else 'MISSED'}")  # fmt: skip
    print(f"nets trained in {trained:.0f} s, all in {time.perf_counter() - start:.0f} s "
          f"(load average at the end {_load()})")  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
