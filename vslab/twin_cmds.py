"""`vslab twin fit`: the twin of the lab's own robot, a description fitted to the lab's dataset (issue 33)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
import yaml
from rich.table import Table

from models.robot import CONFIG_DIR, RobotDescription, RobotDescriptionError, load_robot, robot_path
from vslab.app import _error, _overrides, _robot, console, load_dataset, options, pretraining_twin, twin_app

if TYPE_CHECKING:
    from pipeline.lab import Lab
    from pipeline.popup_fit import PopupLinkFit


@twin_app.command("fit")
def twin_fit(
    dataset: Annotated[
        str | None,
        typer.Option(
            help="The VSL arm's dataset to fit: NAME or NAME@VERSION (its settled points, tracked). "
            "The POPUP arm is fitted to the lab's link tests (popup_static, popup_impact)."
        ),
    ] = None,
    robot: Annotated[
        str, typer.Option(help="The nominal description it extends (a name or a path).")
    ] = "vsl",
    out: Annotated[
        Path | None,
        typer.Option(help="The fitted description's file (default: <lab>/twin/<robot>_fitted.yaml)."),
    ] = None,
) -> None:
    """Fit a description to the lab's robot and write one that extends the nominal one, each value with its
    standard error; what the data cannot identify is named, with why, and left nominal. The VSL arm: its
    static parameters (each link's stiffness table k(p) and hysteresis, the link lengths, joint offsets,
    masses, the servos' torque constant) from a dataset. The POPUP arm: the tested link's Table 1 (k̂, ĉ at
    each tapped pressure, its inertia) from the lab's popup_static and popup_impact sessions."""
    from acquisition.code_version import code_version
    from models.robot import AnthropomorphicKinematics
    from pipeline.twin_fit import TwinFitError, VslStaticFit

    nominal = _robot(robot)
    lab = options().lab
    if out is None and not lab.is_local:
        _error(f"--lab {lab} is on a store: give --out FILE for the fitted description")
    vsl = isinstance(nominal.kinematics, AnthropomorphicKinematics)
    if vsl and dataset is None:
        _error("--dataset: the VSL arm is fitted to a dataset of its settled points: give NAME[@VERSION]")
    if not vsl and dataset is not None:
        _error(f"--dataset: robot {nominal.name} is fitted to its link tests (the lab's popup_static and "
               "popup_impact sessions), not to a dataset")  # fmt: skip
    if vsl:
        data, reference = load_dataset("--dataset", dataset)
        moves = _moves(lab, reference)
        try:
            fit = VslStaticFit(nominal).fit(data, moves)
        except TwinFitError as exc:
            _error(f"--dataset {reference}: {exc}")
        made = fit.description, "pipeline.twin_fit"
    else:
        fit, reference = _popup_fit(nominal, lab)
        made = fit.description, "pipeline.popup_fit"
    target = out if out is not None else Path(str(lab.twin.fitted(nominal.name)))
    base = robot_path(robot)
    extends = nominal.name if base.resolve().parent == CONFIG_DIR.resolve() else os.path.relpath(
        base.resolve(), target.resolve().parent)  # fmt: skip
    fitted = made[0](f"{nominal.name}_fitted", extends, reference, code_version(made[1]))
    text = yaml.safe_dump(fitted, sort_keys=False, allow_unicode=True, width=110, default_flow_style=None)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        said = f"--dataset {reference}" if vsl else "(the link tests)"
        target.write_text(f"# written by `vslab twin fit --robot {robot} {said}`\n{text}")
    except OSError as exc:
        _error(f"--out {target}: cannot be written ({exc.strerror or exc})")
    try:
        load_robot(target)  # what was written must be a description the twin can run
    except RobotDescriptionError as exc:
        target.unlink()
        _error(f"the fitted description is not valid, nothing written: {exc}")
    kept = {"name": fitted["name"], "file": str(target), **fitted["fitted"]}
    _keep(lab.twin.fit(fitted["name"]), kept)  # what the report shows of it
    if not options().quiet:
        table = Table("parameter", "fitted", "± 1 SE", "nominal")
        for row in fit.table().itertuples():
            if not row.why:
                table.add_row(row.parameter, *(f"{v:.6g}" for v in (row.value, row.stderr, row.nominal)))
        console.print(table)
        for parameter, why in fit.not_identifiable_.items():
            console.print(f"not identifiable, left nominal: {parameter}: {why}", highlight=False)
        if vsl:
            console.print(f"tip residual {fit.residual_rms_mm_:.3f} mm per axis over {fit.n_points_} points "
                          f"of {fit.n_sessions_} sessions")  # fmt: skip
            speed = fit.move_speed_rad_s_
            console.print("the loops followed through the arm's moves on its twin at "
                          f"{speed:.3g} rad/s (read from the points' times)" if speed else
                          "the loops followed along straight lines between the points (their times give no "
                          "move speed)", highlight=False)  # fmt: skip
            damping = fit.damping_
            if damping is not None and damping.values_:
                lag_ms = damping.lag_s_ * 1e3
                console.print(f"the links' damping from their swings after {damping.n_moves_} moves: "
                              f"{damping.residual_rms_mm_:.3f} mm per axis left, the tracker "
                              f"{lag_ms:.1f} ms behind the goals' stamps", highlight=False)  # fmt: skip
            field = fit.field_
            console.print(f"the tracker's field is distorted: {field.rms_mm:.2g} mm per axis over "
                          f"{field.length_scale_m * 1e3:.0f} mm (noise {field.noise_mm:.2g} mm), fitted "
                          "beside the arm" if field is not None else
                          "the tracker's field shows no distortion",
                          highlight=False)  # fmt: skip
        else:
            console.print(f"{fit.n_holds_} static holds and {fit.n_taps_} taps of {len(fit.sessions_)} "
                          "sessions")  # fmt: skip
        console.print(f"written: {target}")


def _moves(lab: Lab, reference: str):
    """The dataset's moves into its points (their swings tell the links' damping), or None where it keeps
    none (built before vslab kept them, or its sessions recorded no servo goals)."""
    name, _, version = reference.partition("@")
    path = lab.datasets.path(name, version) / "moves.parquet"
    if not path.exists():
        return None
    try:
        return lab.datasets.load(name, version, table="moves")[0]
    except (OSError, ValueError) as exc:
        _error(f"--dataset {reference}: its moves cannot be read ({type(exc).__name__}: {exc}); build it "
               "again")  # fmt: skip


def _popup_fit(nominal: RobotDescription, lab: Lab) -> tuple[PopupLinkFit, str]:
    """(the fitted ``PopupLinkFit``, what it was fitted to in words) from the lab's link tests of the link
    the static test loaded; one ``error:`` line where a session cannot be read or the tests cannot be
    fitted."""
    import pandas as pd

    from pipeline.link_tests import LinkTestError, impact_taps, static_holds
    from pipeline.popup_fit import PopupLinkFit
    from pipeline.twin_fit import TwinFitError

    rows = {}
    for experiment, read in (("popup_static", static_holds), ("popup_impact", impact_taps)):
        sessions, bad = lab.sessions.select(experiment)
        for name, why in bad.items():
            console.print(f"left out: {name}: {why}", highlight=False, markup=False)
        frames = []
        for d in sessions:
            try:
                frames.append(read(d))
            except LinkTestError as exc:  # damaged, or without its stream
                _error(f"{experiment}: {exc}")
            except Exception as exc:  # events or streams that are not a link test's: one line, named
                _error(f"{experiment}: session {d.name}: not a link test's ({type(exc).__name__}: {exc})")
        rows[experiment] = (pd.concat(frames, ignore_index=True) if frames
                            else pd.DataFrame(columns=["robot", "session_id"]), len(sessions))  # fmt: skip
    holds = rows["popup_static"][0]
    links = sorted(set(holds["link"])) if "link" in holds else []
    if len(links) > 1:
        _error(f"the link tests: the popup_static sessions load links {', '.join(links)}: fit one link's")
    try:
        fit = PopupLinkFit(nominal, links[0] if links else "link2").fit(holds, rows["popup_impact"][0])
    except TwinFitError as exc:
        _error(f"the link tests: {exc}")
    return fit, (f"link tests: {rows['popup_static'][1]} popup_static and {rows['popup_impact'][1]} "
                 "popup_impact sessions")  # fmt: skip


@twin_app.command("check")
def twin_check(
    robot: Annotated[str, typer.Option(help="The description to check (a fitted one: a path).")],
    dataset: Annotated[
        str | None,
        typer.Option(
            help="The VSL arm: a dataset of the lab's robot the fit did not see: NAME[@VERSION]. The POPUP "
            "arm is checked on the lab's link tests (popup_static, popup_impact)."
        ),
    ] = None,
    nominal: Annotated[
        str | None,
        typer.Option(help="The description to compare with (a name or a path; default: vsl, popup)."),
    ] = None,
    repeat: Annotated[
        str | None, typer.Option(help="The dataset's repeat (its points in another order): the floor beside.")
    ] = None,
    seed: Annotated[int, typer.Option(help="POPUP: the seed of the twin's link tests (not the lab's).")] = 1,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set", help="POPUP: the link tests as the lab ran them: popup_impact.taps=3 (repeatable)."
        ),
    ] = None,
) -> None:
    """How well a description predicts the lab's robot beside the nominal description. The VSL arm: a
    dataset's tracked tips, per pressure × payload cell, and (given the dataset's repeat) the floor: what no
    static model predicts. The POPUP arm: the lab's link tests run on each twin and measured as the lab's
    (f_s, ζ, the static stiffness per pressure), each distance in per cent of the lab's value."""
    from models.robot import AnthropomorphicKinematics
    from pipeline.twin_check import twin_check as check
    from pipeline.twin_fit import TwinFitError

    if seed < 0:
        _error(f"--seed must be ≥ 0, got {seed}")
    checked = _robot(robot)
    vsl = isinstance(checked.kinematics, AnthropomorphicKinematics)
    compared = _robot(nominal or ("vsl" if vsl else "popup"))
    if not vsl:
        if dataset is not None or repeat is not None:
            _error(f"--dataset: robot {checked.name} is checked on its link tests (the lab's popup_static "
                   "and popup_impact sessions), not on a dataset")  # fmt: skip
        _popup_check(robot, checked, nominal or "popup", compared, seed, _link_test_overrides(set_ or []))
        return
    if set_:
        _error("--set: the VSL arm's check simulates nothing (it predicts the dataset's settled points)")
    if dataset is None:
        _error("--dataset: the VSL arm is checked on a dataset of its settled points: give NAME[@VERSION]")
    loaded = {
        option: load_dataset(option, reference)
        for option, reference in (("--dataset", dataset), ("--repeat", repeat))
        if reference is not None
    }
    data, repeated = loaded["--dataset"][0], loaded.get("--repeat", (None,))[0]
    try:
        table = check({"nominal": compared, "checked": checked}, data, repeated)
    except TwinFitError as exc:
        _error(f"--dataset {dataset}: {exc}")
    except ValueError as exc:  # the repeat is not this dataset's campaign in another order
        _error(f"--repeat {repeat}: {exc}")
    shown = Table("pressure", "payload g", "n", f"{compared.name} mm", f"{checked.name} mm",
                  *(["floor mm", f"{checked.name} / floor"] if repeat else []))  # fmt: skip
    for row in table.itertuples():
        cells = [row.pressure_bin, "all" if row.payload_g < 0 else f"{row.payload_g:g}", f"{row.n}",
                 f"{row.nominal_mm_mean:.3f}", f"{row.checked_mm_mean:.3f}"]  # fmt: skip
        if repeat:
            cells += [f"{row.floor_mm_mean:.3f}", f"{row.checked_mm_mean / row.floor_mm_mean:.2f}"]
        shown.add_row(*cells)
    console.print(shown)
    made_from = {"robot": robot, "nominal": nominal} | {
        option.removeprefix("--"): reference for option, (_, reference) in loaded.items()
    }
    names = {"checked": checked.name, "nominal": compared.name}
    kept = _keep(options().lab.twin.check(checked.name), {"made_from": made_from, "names": names,
                                                          "table": table.to_dict("records")})  # fmt: skip
    if not options().quiet:
        console.print(f"kept for the report: {kept}", highlight=False)


def _link_test_overrides(pairs: list[str]) -> dict[str, dict]:
    """``--set popup_impact.taps=3`` pairs → {experiment: {key: value}}; one error line for another key."""
    from pipeline.popup_check import TESTS

    tests = [experiment for experiment, _ in TESTS]
    out: dict[str, dict] = {}
    for key, value in _overrides(pairs).items():
        experiment, _, name = key.partition(".")
        if experiment not in tests or not name:
            _error(f"--set {key}: name a link test's parameter: {' or '.join(tests)}.KEY=VALUE")
        out.setdefault(experiment, {})[name] = value
    return out


def _popup_check(robot: str, checked: RobotDescription, nominal: str, compared: RobotDescription,
                 seed: int, overrides: dict[str, dict]) -> None:  # fmt: skip
    """`vslab twin check` of a POPUP description: the lab's link tests measured, then run on the twin of
    each description (in a temporary store) and measured alike; one ``error:`` line where they cannot be."""
    import tempfile

    from acquisition.safety import SafetyError
    from pipeline.lab import Lab
    from pipeline.popup_check import check_summary, popup_check
    from pipeline.twin_fit import TwinFitError

    lab = options().lab
    fit, tests = _popup_fit(compared, lab)  # the lab's link tests, read and measured (errors: one line)
    measured = fit.measured_
    names = {"checked": checked.name, "nominal": compared.name}
    with tempfile.TemporaryDirectory(prefix="vslab-twin-check-") as root:
        try:
            twins = Lab.open(root)  # a lab of its own, thrown away: each twin's tests in its study
            table = popup_check({"nominal": nominal, "checked": robot}, measured, fit.link, twins, seed,
                                overrides)  # fmt: skip
        except TwinFitError as exc:
            _error(str(exc))
        except (ValueError, RobotDescriptionError, SafetyError) as exc:  # a --set the tests refuse
            _error(f"the twin's link tests: {exc}")
    shown = Table("kPa", "quantity", "measured", "± 1 SE", compared.name, "%", checked.name, "%")
    for row in table.itertuples():
        shown.add_row(f"{row.pressure_kpa:g}", row.quantity, *(f"{v:.4g}" for v in (row.measured, row.se)),
                      f"{row.nominal:.4g}", f"{row.nominal_pct:+.2f}", f"{row.checked:.4g}",
                      f"{row.checked_pct:+.2f}")  # fmt: skip
    console.print(shown)
    summary = check_summary(table, ["nominal", "checked"])
    for quantity, row in summary.iterrows():
        console.print(f"{quantity}: rms distance {row['nominal']:.2f} % ({compared.name}), "
                      f"{row['checked']:.2f} % ({checked.name})", highlight=False)  # fmt: skip
    made_from = {"robot": robot, "nominal": nominal, "link_tests": tests, "seed": seed, "set": overrides}
    record = {"kind": "link tests", "made_from": made_from, "names": names, "table": table.to_dict("records")}
    kept = _keep(lab.twin.check(checked.name), record)
    if not options().quiet:
        console.print(f"kept for the report: {kept}", highlight=False)


def _keep(path, record: dict):
    """Write ``record`` as JSON at ``path`` in the lab's twin folder (what the report reads); one error line
    where it cannot be written."""
    try:
        if options().lab.is_local:
            path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record, indent=1, default=float))
    except OSError as exc:
        _error(f"{path}: cannot be written ({exc.strerror or exc})")
    return path


@twin_app.command("curve")
def twin_curve(
    robot: Annotated[
        str, typer.Option(help="The twin to pretrain on (a fitted description's file, or a name).")
    ],
    dataset: Annotated[str, typer.Option(help="The lab's measured dataset: NAME[@VERSION].")],
    direction: Annotated[str, typer.Option(help="The nets' direction: inverse or forward.")] = "inverse",
    preset: Annotated[str, typer.Option(help="A preset of models.hybrid (small-residual, paper, …).")] = (
        "small-residual"
    ),
    split: Annotated[
        str, typer.Option(help="split_group (whole sessions drawn: no test row seen) or split_random.")
    ] = "split_group",
    points: Annotated[
        int | None, typer.Option(help="Points of the twin's campaign (default: the campaign experiment's).")
    ] = None,
    max_epochs: Annotated[
        int, typer.Option(help="Training epochs at most (early stopping ends most).")
    ] = 300,
) -> None:
    """The learning curve of pretraining on the twin: the measured data's test error of a net trained on 1, 2,
    5, 10, 20, 50 and 100 % of the measured train and val rows alone, beside the same net pretrained on the
    twin's campaign and fine-tuned on them. Prints the table and draws <lab>/figures/pretraining_curve."""
    from analysis.twin_report import pretraining_curve
    from models.hybrid import preset as net_preset
    from pipeline.datasets import SPLIT_COLUMNS
    from pipeline.pretrain import curve_verdict, learning_curve, twin_campaign
    from pipeline.train import TrainConfig

    if direction not in ("inverse", "forward"):
        _error(f"--direction {direction}: expected inverse or forward")
    if split not in SPLIT_COLUMNS:
        _error(f"--split {split}: expected one of {', '.join(SPLIT_COLUMNS)}")
    if max_epochs < 1 or (points is not None and points < 10):
        _error("--max-epochs is at least 1 and --points at least 10")
    try:
        net = net_preset(direction, preset)
    except KeyError as exc:
        _error(f"--preset {preset}: {exc.args[0]}")
    pretraining_twin("--robot", robot)
    lab = options().lab
    measured, reference = load_dataset("--dataset", dataset)
    say = (lambda _: None) if options().quiet else (lambda text: console.print(text, highlight=False))
    say(f"the twin's campaign on {robot}: simulating and building …")
    report = twin_campaign(lab, robot, points=points)
    twin, _ = lab.datasets.load(report.name, report.version)
    config = TrainConfig(net=net, split=split, max_epochs=max_epochs)
    try:
        curve = learning_curve(measured, twin, config, robot=robot, progress=say)
    except ValueError as exc:  # PretrainError; a dataset without the columns the nets need
        _error(f"--dataset {reference}: {exc}")
    made_from = {"measured": reference, "twin": f"{report.name}@{report.version}", "robot": robot}
    drawn = pretraining_curve(curve, Path(str(lab.figures)), made_from=made_from)
    net_name = f"{direction}-{preset}"
    _keep(lab.twin.curve, {"made_from": made_from, "net": net_name, "split": split,
                           "curve": curve.to_dict("records")})  # fmt: skip
    table = Table(
        "measured rows", "train", "val", "alone mm", "pretrained mm", "alone mrad", "pretrained mrad"
    )
    for row in curve.to_dict("records"):
        share = f"{row['fraction']:.0%}" if row["fraction"] else "none (twin only)"
        cells = [share, f"{row['train_rows']:,}", f"{row['val_rows']:,}"]
        for key in ("measured_only_tip_mean_mm", "fine_tuned_tip_mean_mm", "measured_only_joint_mean_mrad",
                    "fine_tuned_joint_mean_mrad"):  # fmt: skip
            value = row.get(key, float("nan"))
            cells.append("" if value != value else f"{value:.3f}")
        table.add_row(*cells)
    console.print(table)
    verdict = curve_verdict(curve)
    said = (f"pretrained on the twin, fine-tuned on 10 % ({verdict['rows']:,} rows): "
            f"{verdict['fine_tuned']:.3f} mm; alone on all {verdict['all_rows']:,}: "
            f"{verdict['all_measured']:.3f} mm (ratio {verdict['ratio']:.2f})")  # fmt: skip
    console.print(said, highlight=False)
    console.print(f"drawn: {drawn['png']}", highlight=False)
