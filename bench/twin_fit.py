"""The twin fit's time on the paper-size campaign (issue 33): `pipeline.twin_fit.VslStaticFit` on the
17,568 settled points of a campaign simulated on the nominal VSL twin (128 benches) and the moves into them
(the links' damping, `pipeline.damping_fit`), beside its target (under 60 s on 2 cores; the statics' time
and the damping's printed apart), with the machine's load average and each fitted value against the
description it was simulated with.

    python bench/twin_fit.py [--points N] [--benches B] [--lab DIR] [--arm bench/lab_arm.yaml]

``--lab DIR``: a lab whose ``campaign`` dataset is fitted (simulated and built there first if it has none).
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

TARGET_S = 60.0


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _true(arm, parameter: str) -> float:
    """The value of a fitted parameter's name (``pipeline.twin_fit``) in the description ``arm``."""
    from models.robot import load_robot
    from pipeline.arm_history import mass_bodies
    from pipeline.twin_fit import OFFSETS, STRAIN

    if parameter.startswith("creep.fraction@"):  # a creep element's fraction, by its time constant
        creep = arm.effects.creep
        times = dict(zip(creep.time_constants_s, creep.fractions, strict=True)) if creep else {}
        return times.get(float(parameter.removeprefix("creep.fraction@").removesuffix("s")), 0.0)
    if parameter.endswith(".damping_scale"):  # the link's damping table against the papers' arm's
        link = parameter.removesuffix(".damping_scale")
        return (
            arm.link_table(link).damping_nms_per_rad[0]
            / load_robot("vsl").link_table(link).damping_nms_per_rad[0]
        )
    if parameter == STRAIN:
        return arm.effects.elongation.strain_per_bar if arm.effects.elongation else 0.0
    if parameter.startswith("servo."):  # the torque constant, the servos' stiffness and backlash
        return getattr(arm.servo, parameter.removeprefix("servo."))
    if ".hose_" in parameter:  # a joint's hoses: none is 0
        joint, _, field = parameter.partition(".hose_")
        hoses = arm.effects.hoses.joints if arm.effects.hoses else {}
        return getattr(hoses[joint], field) if joint in hoses else 0.0
    if parameter.endswith(".mass_scale"):  # the body's mass against the papers' arm's
        nominal = load_robot("vsl")
        body = mass_bodies(nominal, [nominal.link_of(v) for v in nominal.virtual_joints])[parameter[:-11]]
        return sum(m.mass_kg for m in arm.masses if m.name in body) / sum(
            m.mass_kg for m in nominal.masses if m.name in body)  # fmt: skip
    subject, _, field = parameter.partition(".")
    if not field:
        return getattr(arm.kinematics, subject)
    if field == "offset_rad":
        return arm.kinematics.joint_offsets_rad[OFFSETS.index(subject)]
    if field.startswith("k@"):
        table = arm.link_table(subject)
        return dict(zip([f"{p / 1e5:g}bar" for p in table.pressure_pa], table.stiffness_nm_per_rad,
                        strict=True))[field[2:]]  # fmt: skip
    return getattr(next(link for link in arm.links if link.name == subject).hysteresis, field)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=17568, help="campaign points (the paper's n = 17568)")
    parser.add_argument("--benches", type=int, default=128, help="campaign sessions (twin benches)")
    parser.add_argument("--lab", type=Path, default=None, help="a lab to fit (its campaign dataset)")
    parser.add_argument("--seed", type=int, default=0, help="the campaign's seed")
    parser.add_argument("--arm", default="vsl", help="the arm the campaign is simulated on (the fit's truth; "
                        "bench/lab_arm.yaml: a lab's arm the fit is not told about)")  # fmt: skip
    args = parser.parse_args()

    from acquisition.recorder.sessions import SessionStore
    from models.robot import load_robot
    from pipeline.build import build
    from pipeline.dataset_store import DatasetError
    from pipeline.lab import Lab
    from pipeline.twin_fit import VslStaticFit
    from twin.runner import simulate_experiment

    print(f"bench/twin_fit.py on {os.cpu_count()} cores, load average at the start {_load()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="twin-fit-") as scratch:
        where = args.lab or Path(scratch) / "lab"
        lab = Lab(where)
        try:
            data, _ = lab.datasets.load("campaign")
        except DatasetError:
            start = time.perf_counter()
            overrides = {"points": args.points, "robot": args.arm}
            simulate_experiment("campaign", SessionStore(where / "sessions"), benches=args.benches,
                                seed=args.seed, overrides=overrides)  # fmt: skip
            report = build(sorted((where / "sessions").iterdir()), lab, "campaign")
            data, _ = lab.datasets.load("campaign", report.version)
            print(f"campaign simulated and built: {time.perf_counter() - start:.1f} s", flush=True)
        try:  # the moves into the points: the links' damping (a dataset built before they were kept has none)
            moves = lab.datasets.load("campaign", table="moves")[0]
        except FileNotFoundError:
            moves = None
        start = time.perf_counter()
        nominal = load_robot("vsl")  # under the simulated arm's name: the lab records under its own
        fit = VslStaticFit(nominal.model_copy(update={"name": load_robot(args.arm).name})).fit(data, moves)
        took = time.perf_counter() - start
    table = fit.table()
    table["true"] = [_true(load_robot(args.arm), name) for name in table["parameter"]]
    table["off_%"] = 100 * (table["value"] / table["true"] - 1)
    table["off_se"] = (table["value"] - table["true"]) / table["stderr"]
    print(table.drop(columns="why").to_string(index=False, float_format=lambda v: f"{v:.6g}"))
    print(f"not identifiable: {', '.join(fit.not_identifiable_)}")
    verdict = "ok" if took < TARGET_S else "MISSED"
    damping = fit.damping_
    if damping is not None and damping.n_moves_:
        print(f"damping from {damping.n_moves_} moves: {damping.seconds_:.1f} s of the fit; the swings left "
              f"{damping.residual_rms_mm_:.3f} mm per axis; stiffness from their frequency "
              + ", ".join(f"{k} ×{f:.4f} ± {e:.4f}" for k, (f, e) in damping.stiffness_.items()))  # fmt: skip
    statics = took - (damping.seconds_ if damping is not None else 0.0)
    print(f"\nfit of {fit.n_points_:,} points ({fit.n_sessions_} sessions): {took:.1f} s (the statics "
          f"{statics:.1f} s, the damping {took - statics:.1f} s)   "
          f"target < {TARGET_S:.0f} s {verdict}   (load {_load()}; tip residual "
          f"{fit.residual_rms_mm_:.3f} mm per axis)")  # fmt: skip
    return 0 if took < TARGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
