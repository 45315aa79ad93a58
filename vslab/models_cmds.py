"""`vslab train` and `vslab models`: grid training into <lab>/models/ and the trained versions."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Column, Table

from vslab.app import Settings, _fail, _overrides, app, console

models_app = typer.Typer(help="Trained networks in <lab>/models/.", no_args_is_help=True)
app.add_typer(models_app, name="models")

VERSION = Column("version", no_wrap=True, min_width=16)  # always whole: it is what `models show` takes
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
    workers: Annotated[int, typer.Option(help="Parallel training processes (0: one per core).")] = 0,
) -> None:
    """Train every job of a grid whose version is not in <lab>/models yet (a second run trains nothing)."""
    import concurrent.futures as cf
    import multiprocessing

    from acquisition.processes import lower_priority

    lower_priority()  # batch work (and its worker processes): a recording on this computer goes first

    from rich.progress import Progress

    from pipeline.grid import GridError, expand, load_grid, run_grid

    try:
        spec = load_grid(grid, _overrides(set_ or []))
        n_jobs = len(expand(Settings.lab, spec))
    except GridError as exc:
        _fail(str(exc))
    executor = None
    if workers > 1:
        executor = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("forkserver"))
    start = time.perf_counter()
    with Progress(console=console, disable=Settings.quiet, transient=True) as bar:
        task = bar.add_task(f"{n_jobs} training jobs", total=n_jobs)

        def progress(done: int, total: int, summary: dict) -> None:
            bar.update(task, completed=done, description=f"{summary['name']} {summary['status']}")

        try:
            results = run_grid(
                Settings.lab, spec, executor=executor, progress=progress, workers=workers or None
            )
        except (GridError, ValueError, FileNotFoundError) as exc:
            _fail(str(exc))
        finally:
            if executor is not None:
                executor.shutdown(cancel_futures=True)
    title = f"{len(results)} models in {Settings.lab / 'models'}"
    table = Table(VERSION, "model", "dataset", "split", "seed", "test mean mm", "test p95 mm", "epochs",
                  "time s", "status", title=title)  # fmt: skip
    for r in results:
        table.add_row(r["version"], r["name"], r["dataset"], r["split"], str(r["seed"]),
                      _mm(r["test_mean_mm"]), _mm(r["test_p95_mm"]), str(r["epochs"]),
                      f"{r['train_time_s']:.1f}", r["status"])  # fmt: skip
    console.print(table)
    trained = sum(r["status"] == "trained" for r in results)
    console.print(
        f"{trained} trained, {len(results) - trained} existing, in {time.perf_counter() - start:.1f} s"
    )


@models_app.command("list")
def models_list() -> None:
    """List the trained versions (oldest first) with their test tip error."""
    from pipeline.registry import list_models

    rows = list_models(Settings.lab / "models")
    if not rows:
        console.print(f"no models in {Settings.lab / 'models'} (train some: `vslab train`)")
        return
    table = Table(VERSION, "model", "dataset", "split", "seed", "test mean mm", "test p95 mm", "created")
    for r in rows:
        table.add_row(r["version"], r["name"], r["dataset"], str(r["split"]), str(r["seed"]),
                      _mm(r["test_mean_mm"]), _mm(r["test_p95_mm"]), str(r["created"]))  # fmt: skip
    console.print(table)


@models_app.command("show")
def models_show(
    version: Annotated[str, typer.Argument(help="Model version (a unique prefix will do).")],
) -> None:
    """A model's card: lineage, configuration, test metrics and the per-cell table."""
    from pipeline.registry import find, load_card

    try:
        path = find(Settings.lab / "models", version)
    except (FileNotFoundError, ValueError) as exc:
        _fail(str(exc))
    card = load_card(path)
    metrics = dict(card.get("metrics", {}))
    cells = metrics.pop("per_cell", [])
    console.print(f"[bold]{card['name']} {card['version']}[/]  → {path}", highlight=False)
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


@models_app.command("compare")
def models_compare(
    versions: Annotated[list[str], typer.Argument(help="Model versions (unique prefixes will do).")],
) -> None:
    """Versions side by side: configuration and test metrics."""
    from pipeline.registry import compare

    try:
        df = compare(Settings.lab / "models", versions)
    except (FileNotFoundError, ValueError) as exc:
        _fail(str(exc))
    table = Table("", *(Column(v, no_wrap=True, min_width=len(v)) for v in df.index), title="models compared")
    for column in df.columns:
        if column in ("created",):
            continue
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in df[column]]
        table.add_row(column, *cells)
    console.print(table)
