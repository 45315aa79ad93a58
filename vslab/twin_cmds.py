"""`vslab twin fit`: the twin of the lab's own robot, a description fitted to the lab's dataset (issue 33)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
import yaml
from rich.table import Table

from models.robot import CONFIG_DIR, RobotDescriptionError, load_robot, robot_path
from vslab.app import _error, _robot, console, load_dataset, options, twin_app


@twin_app.command("fit")
def twin_fit(
    dataset: Annotated[
        str,
        typer.Option(help="The lab's dataset to fit: NAME or NAME@VERSION (its settled points, tracked)."),
    ],
    robot: Annotated[
        str, typer.Option(help="The nominal description it extends (a name or a path).")
    ] = "vsl",
    out: Annotated[
        Path | None,
        typer.Option(help="The fitted description's file (default: <lab>/twin/<robot>_fitted.yaml)."),
    ] = None,
) -> None:
    """Fit the VSL arm's static parameters (each link's stiffness table k(p) and hysteresis, the link lengths)
    to a dataset of the lab's robot and write a description that extends the nominal one, each value with its
    standard error; what the data cannot identify is named, with why, and left nominal."""
    from acquisition.code_version import code_version
    from pipeline.twin_fit import TwinFitError, VslStaticFit

    nominal = _robot(robot)
    lab = options().lab
    data, reference = load_dataset("--dataset", dataset)
    try:
        fit = VslStaticFit(nominal).fit(data)
    except TwinFitError as exc:
        _error(f"--dataset {reference}: {exc}")
    if out is None and not lab.is_local:
        _error(f"--lab {lab} is on a store: give --out FILE for the fitted description")
    target = out if out is not None else Path(str(lab.twin)) / f"{nominal.name}_fitted.yaml"
    base = robot_path(robot)
    extends = nominal.name if base.resolve().parent == CONFIG_DIR.resolve() else os.path.relpath(
        base.resolve(), target.resolve().parent)  # fmt: skip
    fitted = fit.description(f"{nominal.name}_fitted", extends, reference,
                             code_version("pipeline.twin_fit"))  # fmt: skip
    text = yaml.safe_dump(fitted, sort_keys=False, allow_unicode=True, width=110, default_flow_style=None)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(f"# written by `vslab twin fit --robot {robot} --dataset {reference}`\n{text}")
    except OSError as exc:
        _error(f"--out {target}: cannot be written ({exc.strerror or exc})")
    try:
        load_robot(target)  # what was written must be a description the twin can run
    except RobotDescriptionError as exc:
        target.unlink()
        _error(f"the fitted description is not valid, nothing written: {exc}")
    if not options().quiet:
        table = Table("parameter", "fitted", "± 1 SE", "nominal")
        for row in fit.table().itertuples():
            if not row.why:
                table.add_row(row.parameter, *(f"{v:.6g}" for v in (row.value, row.stderr, row.nominal)))
        console.print(table)
        for parameter, why in fit.not_identifiable_.items():
            console.print(f"not identifiable, left nominal: {parameter}: {why}", highlight=False)
        console.print(f"tip residual {fit.residual_rms_mm_:.3f} mm per axis over {fit.n_points_} points "
                      f"of {fit.n_sessions_} sessions")  # fmt: skip
        console.print(f"written: {target}")


@twin_app.command("check")
def twin_check(
    robot: Annotated[str, typer.Option(help="The description to check (a fitted one: a path).")],
    dataset: Annotated[
        str, typer.Option(help="A dataset of the lab's robot the fit did not see: NAME[@VERSION].")
    ],
    nominal: Annotated[str, typer.Option(help="The description to compare with (a name or a path).")] = "vsl",
    repeat: Annotated[
        str | None, typer.Option(help="The dataset's repeat (its points in another order): the floor beside.")
    ] = None,
) -> None:
    """How well a description predicts a dataset's tracked tips, per pressure × payload cell, beside the
    nominal description's and (given the dataset's repeat) the floor: what no static model predicts."""
    from pipeline.twin_check import twin_check as check
    from pipeline.twin_fit import TwinFitError

    checked, compared = _robot(robot), _robot(nominal)
    loaded = {
        option: load_dataset(option, reference)[0]
        for option, reference in (("--dataset", dataset), ("--repeat", repeat))
        if reference is not None
    }
    try:
        table = check({"nominal": compared, "checked": checked}, loaded["--dataset"], loaded.get("--repeat"))
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
