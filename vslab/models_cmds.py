"""`vslab train` and `vslab models`: grid training into <lab>/models/ and the trained versions."""

from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Column, Table

from vslab.app import _error, _overrides, app, console, load_dataset, options, pretraining_twin

models_app = typer.Typer(help="Trained networks in <lab>/models/.", no_args_is_help=True)
app.add_typer(models_app, name="models")


def _version() -> Column:
    """The version column, always whole (it is what `models show` takes); a new one per table: a rich Column
    keeps the cells of the table it was in."""
    return Column("version", no_wrap=True, min_width=16)


GRID = Path(__file__).resolve().parents[1] / "configs" / "train" / "grid.yaml"


def _mm(value) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.2f}"


@app.command()
def train(
    grid: Annotated[Path, typer.Option(help="Grid of models × datasets × splits × seeds (YAML).")] = GRID,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override: a grid key (seeds=[0,1]) or a training field (max_epochs=5)."),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(
            help="Parallel training processes, each net on cores / N threads (0: the small nets one "
            "per core, then each large net alone on every core)."
        ),
    ] = 0,
    cluster: Annotated[
        str | None,
        typer.Option(
            help="A Dask scheduler (tcp://host:port) whose workers train the jobs, one torch thread "
            "each; they must see the lab at the same path, or the same store (vslab[cluster])."
        ),
    ] = None,
    pretrain: Annotated[
        str | None,
        typer.Option(
            help="A description of the arm (a fitted twin's file from `vslab twin fit`, or a name): each "
            "net first learns a campaign simulated on it (dataset twin-<name>), then fine-tunes on the "
            "grid's data."
        ),
    ] = None,
    pretrain_points: Annotated[
        int | None, typer.Option(help="Points of the twin's campaign (default: the campaign experiment's).")
    ] = None,
) -> None:
    """Train every job of a grid whose version is not in <lab>/models yet (a second run trains nothing)."""
    import concurrent.futures as cf
    import multiprocessing

    from rich.progress import Progress

    from pipeline.cluster import ClusterError, cluster_executor
    from pipeline.grid import expand, load_grid, run_grid

    if workers < 0:
        _error(f"--workers must be ≥ 0 (0: the small nets one per core, the large ones alone), got {workers}")
    overrides = _overrides(set_ or [])
    if pretrain_points is not None and (pretrain is None or pretrain_points < 10):
        _error("--pretrain-points: the points of the twin's campaign for --pretrain (an integer ≥ 10)")
    try:
        spec = load_grid(grid, overrides)
        expand(options().lab, spec)  # the grid and its datasets checked before the twin is simulated
        twin = _twin_campaign(pretrain, pretrain_points) if pretrain is not None else None
        n_jobs = len(expand(options().lab, spec, twin))
    except (ValueError, OSError) as exc:  # GridError; a damaged model already in the lab
        _error(str(exc))
    if cluster is not None and workers:
        _error("--workers and --cluster: the cluster's workers train (give one of them)")
    from acquisition.processes import lower_priority

    lower_priority()  # arguments checked; batch work (and its workers): a recording here goes first
    start = time.perf_counter()
    with (
        contextlib.ExitStack() as stack,
        Progress(console=console, disable=options().quiet, transient=True) as bar,
    ):
        task = bar.add_task(f"{n_jobs} training jobs", total=n_jobs)

        def progress(done: int, total: int, summary: dict) -> None:
            bar.update(task, completed=done, description=f"{summary['name']} {summary['status']}")

        try:
            executor, threads = None, None
            if cluster is not None:
                executor, threads = stack.enter_context(cluster_executor(cluster)), 1
            elif workers > 1:
                executor = cf.ProcessPoolExecutor(
                    workers, mp_context=multiprocessing.get_context("forkserver")
                )
                stack.callback(executor.shutdown, cancel_futures=True)
            results = run_grid(options().lab, spec, executor=executor, progress=progress,
                               workers=workers or None, threads=threads, pretrain=twin)  # fmt: skip
        # GridError; a damaged model or dataset; a full disk; no cluster at the address
        except (ValueError, OSError, ClusterError) as exc:
            bar.stop()
            _error(str(exc))
    title = f"{len(results)} models in {options().lab.models.root}"
    table = Table(_version(), "model", "dataset", "split", "seed", "test mean mm", "test p95 mm", "epochs",
                  "time s", "status", title=title)  # fmt: skip
    for r in results:
        table.add_row(r["version"], r["name"], r["dataset"], r["split"], str(r["seed"]),
                      _mm(r["test_mean_mm"]), _mm(r["test_p95_mm"]), str(r["epochs"]),
                      f"{r['train_time_s']:.1f}", r["status"])  # fmt: skip
    console.print(table)
    if tagged := {r["tag"]: r["version"] for r in results if "tag" in r}:
        console.print("tagged: " + ", ".join(f"{tag} → {version}" for tag, version in tagged.items()))
    trained = sum(r["status"] == "trained" for r in results)
    console.print(
        f"{trained} trained, {len(results) - trained} existing, in {time.perf_counter() - start:.1f} s"
    )


def _twin_campaign(robot: str, points: int | None) -> dict:
    """The twin's campaign for ``vslab train --pretrain``: simulated on ``robot`` and built (what is there
    already is kept), as ``run_grid`` takes it; one error line for a description it cannot be."""
    from pipeline.pretrain import twin_campaign

    description = pretraining_twin("--pretrain", robot)
    if not options().quiet:
        console.print(f"the twin's campaign on {description.name} ({robot}): simulating and building …",
                      highlight=False)  # fmt: skip
    report = twin_campaign(options().lab, robot, points=points)
    where = Path(robot)  # a file: by its whole path (a pool's or a cluster's worker may start elsewhere)
    return {
        "dataset": f"{report.name}@{report.version}",
        "robot": str(where.resolve()) if where.is_file() else robot,
    }


@models_app.command("list")
def models_list() -> None:
    """List the trained versions (oldest first) with their test tip error. Every version's files are checked
    against its card: a damaged one is listed as damaged, with a `warning:` line saying which file and why."""
    from rich.markup import escape

    from pipeline.model_store import ModelStoreError

    models = options().lab.models
    root = models.root
    try:
        rows = models.list()
        tagged = models.tags()
    except OSError as exc:
        _error(f"{root}: cannot be listed ({exc.strerror or exc})")
    except ModelStoreError as exc:
        _error(str(exc))
    if not rows:
        console.print(f"no models in {root} (train some: `vslab train`)", highlight=False, markup=False)
        return
    table = Table(_version(), "model", "dataset", "split", "seed", "test mean mm", "test p95 mm", "created")
    for r in rows:
        if "damaged" in r:
            table.add_row(escape(r["version"]), escape(r["name"]), "[red]damaged[/]", *["–"] * 5)
            continue
        table.add_row(r["version"], r["name"], r["dataset"], str(r["split"]), str(r["seed"]),
                      _mm(r["test_mean_mm"]), _mm(r["test_p95_mm"]), str(r["created"]))  # fmt: skip
    console.print(table)
    if tagged:
        console.print("tags: " + ", ".join(f"{n} → {v}" for n, v in sorted(tagged.items())), highlight=False,
                      markup=False, soft_wrap=True)  # fmt: skip
    for r in rows:
        if "damaged" in r:
            console.print(f"[yellow]warning:[/] model {escape(r['name'])}/{escape(r['version'])} is damaged: "
                          f"{escape(r['damaged'])}", soft_wrap=True, highlight=False)  # fmt: skip


@models_app.command("tag")
def models_tag(
    name: Annotated[str, typer.Argument(help="The tag: a lower-case name, e.g. 'inverse'.")],
    version: Annotated[str, typer.Argument(help="Model version (or a unique prefix, or another tag).")],
) -> None:
    """Give a model version a name that any command taking a version accepts (`--inverse-model NAME`,
    `models show NAME`); a tag that exists is moved. Tags live in <lab>/models/tags.json."""
    from pipeline.model_store import ModelStoreError

    try:
        full = options().lab.models.tag(name, version)
    except (FileNotFoundError, ValueError, ModelStoreError) as exc:  # unknown, ambiguous, damaged, bad name
        _error(str(exc))
    console.print(f"{name} → {full}", highlight=False, markup=False)


def _checked(version: str) -> tuple[Path, dict]:
    """(directory, card) of ``version`` once every file is checked; one error line otherwise."""
    from pipeline.model_store import check_model

    try:
        path = options().lab.models.find(version)
        return path, check_model(path)
    except (FileNotFoundError, ValueError) as exc:  # unknown, ambiguous, damaged (ModelIntegrityError)
        _error(str(exc))


@models_app.command("show")
def models_show(
    version: Annotated[str, typer.Argument(help="Model version (a unique prefix or a tag will do).")],
) -> None:
    """A model's card: lineage, configuration, test metrics and the per-cell table (every file checked first:
    a damaged version is one error line)."""
    from rich.markup import escape

    path, card = _checked(version)
    metrics = dict(card.get("metrics", {}))
    cells = metrics.pop("per_cell", [])
    console.print(f"[bold]{escape(card['name'])} {escape(card['version'])}[/]  → {escape(str(path))}",
                  highlight=False)  # fmt: skip
    lineage = {k: card.get(k) for k in ("dataset", "code_version", "torch", "created", "train_time_s",
                                         "epoch_time_s", "best_epoch", "threads")}  # fmt: skip
    training = {k: v for k, v in card.get("train_config", {}).items() if k != "net"}
    console.print_json(json.dumps({**lineage, "epochs": len(card.get("curves", [])), "net": card["net"],
                                   "training": training}))  # fmt: skip
    table = Table("metric", "value", title="test")
    for key, value in metrics.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    console.print(table)
    if cells:
        cols = list(cells[0])
        cell_table = Table(*cols, title="per cell (link pressure bin × payload)")
        for cell in cells:
            cell_table.add_row(
                *(f"{cell[c]:.3g}" if isinstance(cell[c], float) else str(cell[c]) for c in cols)
            )
        console.print(cell_table)
    if comparison := card.get("comparison"):
        _show_comparison(comparison)


def _show_comparison(comparison: dict) -> None:
    """The comparison a model was trained for: every model of its direction and the floor, per cell."""
    import pandas as pd

    from pipeline.comparison import wide_tables

    for direction, wide in wide_tables(pd.DataFrame(comparison["records"])).items():
        title = (f"{direction} models compared on {comparison['split']}'s test part (mean tip error, mm; "
                 f"this one: {comparison['model']})")  # fmt: skip
        table = Table("cell", *wide.columns, title=title)
        for cell, row in wide.iterrows():
            values = [str(int(row["n"])), *("" if v != v else f"{v:.3f}" for v in row.iloc[1:])]
            table.add_row(str(cell), *values)
        console.print(table)


@models_app.command("compare")
def models_compare(
    versions: Annotated[list[str], typer.Argument(help="Model versions (unique prefixes will do).")],
) -> None:
    """Versions side by side: configuration and test metrics."""
    try:
        df = options().lab.models.compare(versions)
    except (FileNotFoundError, ValueError) as exc:  # unknown, ambiguous, damaged (ModelIntegrityError)
        _error(str(exc))
    table = Table("", *(Column(v, no_wrap=True, min_width=len(v)) for v in df.index), title="models compared")
    for column in df.columns:
        if column in ("created",):
            continue
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in df[column]]
        table.add_row(column, *cells)
    console.print(table)


_TRACKING_HELP = (
    "Where MLflow tracks (default: $MLFLOW_TRACKING_URI, else sqlite:///<lab>/mlflow/mlflow.db with "
    "artifacts beside it)."
)


def _writable(folder: Path, what: str) -> None:
    """Create ``folder`` and write a file in it, or one error line naming it: a read-only lab is said before
    any work, not as a traceback (as root, permission bits do not stop a write; a read-only mount does)."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        _error(f"{folder}: cannot be written, {what} goes there ({exc.strerror or exc})")


@models_app.command("export-mlflow")
def models_export_mlflow(
    tracking_uri: Annotated[str | None, typer.Option(help=_TRACKING_HELP)] = None,
    experiment: Annotated[str, typer.Option(help="The MLflow experiment the runs go in.")] = "vslab",
) -> None:
    """Log every model version as an MLflow run (parameters, test metrics per cell, learning curves, the
    card, weights and ONNX file, the dataset as an input); versions exported before are skipped."""
    import os

    from pipeline.mlflow_export import MlflowExportError, export_models

    lab = options().lab
    artifacts = None
    uri = tracking_uri or os.environ.get("MLFLOW_TRACKING_URI")
    if uri is None:
        if not lab.is_local:
            _error(
                f"--lab {lab} is on a store: give --tracking-uri (an MLflow server or a local "
                "sqlite:///… file)"
            )
        uri = f"sqlite:///{lab.mlflow.resolve() / 'mlflow.db'}"
    if uri.startswith("sqlite:///"):  # a local store: its artifacts beside it (MLflow's default: ./mlruns)
        folder = Path(uri.removeprefix("sqlite:///")).resolve().parent
        _writable(folder, "the MLflow store")
        artifacts = (folder / "artifacts").as_uri()
    try:
        report = export_models(lab.models.root, lab.datasets.root, uri, experiment, artifacts)
    except MlflowExportError as exc:
        _error(str(exc))
    except OSError as exc:
        _error(f"{exc.filename or lab}: cannot be read ({exc.strerror or exc})")
    for line in report.damaged:
        console.print(
            f"warning: not exported, damaged: {line}", highlight=False, markup=False, soft_wrap=True
        )
    if not options().quiet:
        console.print(
            f"{len(report.logged)} run(s) logged, {len(report.skipped)} already there, in experiment "
            f"{experiment!r} at {uri}",
            highlight=False,
            markup=False,
            soft_wrap=True,
        )


_SPLITS = ("split_group", "split_random")


@app.command("compare-models")
def compare_models_command(
    dataset: Annotated[
        str, typer.Argument(help="A campaign dataset: NAME or NAME@VERSION (newest if none).")
    ],
    repeat: Annotated[
        str | None,
        typer.Option(
            help="The same campaign run again from other histories (visit_order=shuffled): the floor."
        ),
    ] = None,
    split: Annotated[str, typer.Option(help="The split to score on: split_group or split_random.")] = _SPLITS[
        0
    ],
    epochs: Annotated[
        int, typer.Option(min=1, help="Most epochs the networks train (early stopping).")
    ] = 300,
    seed: Annotated[int, typer.Option(help="Seed of the networks' training.")] = 0,
) -> None:
    """Every model of the arm on one campaign's test rows, forward and inverse, overall and per pressure ×
    payload cell: rigid, grey box, gradient boosting, history-aware, the paper, residual and small residual
    networks (trained here), and the floor when --repeat gives the campaign's repeat. The card goes to
    <lab>/comparisons/NAME@VERSION.json."""
    from acquisition.plans.experiments import arm_lengths
    from models.robot import AnthropomorphicKinematics, RobotDescriptionError, load_robot
    from pipeline.comparison import compare_models, comparison_markdown, save_compared

    lab = options().lab
    if split not in _SPLITS:
        _error(f"--split {split!r}: expected one of {', '.join(_SPLITS)}")
    loaded = {
        option: load_dataset(option, reference)
        for option, reference in (("DATASET", dataset), ("--repeat", repeat))
        if reference is not None
    }
    data, dataset_ref = loaded["DATASET"]
    if "--repeat" in loaded and loaded["--repeat"][1] == dataset_ref:
        _error(f"--repeat {repeat}: is DATASET itself ({dataset_ref}); the repeat is the campaign run again")
    robots = sorted(set(data["robot"].astype(str))) if "robot" in data else []
    try:
        robot = load_robot(robots[0]) if len(robots) == 1 else None
    except RobotDescriptionError as exc:
        _error(f"DATASET {dataset_ref}: {exc}")
    if robot is None or not isinstance(robot.kinematics, AnthropomorphicKinematics):
        _error(f"DATASET {dataset_ref}: robot(s) {robots}: the comparison needs one VSL-type arm's campaign")
    lengths = arm_lengths(robot)
    repeat_data = loaded["--repeat"][0] if "--repeat" in loaded else None
    say = (
        (lambda _: None)
        if options().quiet
        else (lambda line: console.print(line, highlight=False, markup=False))
    )
    try:
        nets: dict = {}
        table = compare_models(data, lengths, repeat_data, split, {"max_epochs": epochs}, seed, say, nets)
    except (KeyError, ValueError) as exc:  # not a campaign, a repeat of another campaign, too few rows
        _error(f"{dataset_ref}: {exc}")
    made_from = {"dataset": dataset_ref} | ({"repeat": loaded["--repeat"][1]} if "--repeat" in loaded else {})
    made_from["training"] = json.dumps({"max_epochs": epochs, "seed": seed})
    name, _, version = dataset_ref.partition("@")
    dataset = {"name": name, "version": version}
    path = lab.comparisons.path(dataset_ref)
    models = save_compared(path, lab.models, data, dataset, table, nets, made_from, split)
    console.print(comparison_markdown(table), highlight=False, markup=False, soft_wrap=True)
    if not options().quiet:
        console.print(f"card: {path}", highlight=False, markup=False, soft_wrap=True)
        for m in models:
            console.print(f"saved: {m['name']} {m['version']}", highlight=False, markup=False)
