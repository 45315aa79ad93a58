"""The `vslab` command: wiring only — parse options, call the packages, show results."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from models.robot import CONFIG_DIR, RobotDescriptionError
from vslab import (
    cluster_cmds,  # noqa: F401  (registers cluster on the app)
    devices_cmds,  # noqa: F401  (registers devices on the app)
    models_cmds,  # noqa: F401  (registers train and models on the app)
    recording,  # noqa: F401  (registers record and run on the app)
    sessions_cmds,  # noqa: F401  (registers sessions on the app)
    twin_cmds,  # noqa: F401  (registers twin fit on the app)
)
from vslab.app import (
    HISTORY_NOT_STORED,
    _error,
    _fail,
    _overrides,
    _robot,
    app,
    console,
    inverse_model_version,
    load_inverse_model,
    local_lab,
    options,
    robots_app,
    twin_app,
)


@robots_app.command("list")
def robots_list() -> None:
    """List the robot descriptions shipped in configs/robots/."""
    table = Table("name", "description", "actuated", "virtual joints")
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        robot = _robot(str(path))
        table.add_row(
            robot.name, robot.description, " ".join(robot.actuated_joints), " ".join(robot.virtual_joints)
        )
    console.print(table)


@robots_app.command("show")
def robots_show(name: Annotated[str, typer.Argument(help="Robot name or path to a YAML file.")]) -> None:
    """Validate a robot description and print it as JSON (SI units)."""
    robot = _robot(name)
    console.print_json(robot.model_dump_json())


@robots_app.command("urdf")
def robots_urdf(
    name: Annotated[str, typer.Argument(help="Robot name or path to a YAML file.")],
    out: Annotated[Path | None, typer.Option(help="Write it to this file (default: print it).")] = None,
) -> None:
    """The robot's URDF, virtual joints included: what Foxglove and ROS tools draw the arm from."""
    from models.urdf import robot_urdf

    text = robot_urdf(_robot(name))
    if out is None:
        typer.echo(text, nl=False)
        return
    try:
        out.write_text(text)
    except OSError as exc:
        _error(f"cannot write {out}: {exc.strerror or exc}")
    if not options().quiet:
        console.print(f"written: {out}")


@app.command("schema")
def schema_command(
    name: Annotated[str, typer.Argument(help="robot, experiment, grid or experiment-<kind>.")],
    out: Annotated[Path | None, typer.Option(help="Write it to this file (default: print it).")] = None,
) -> None:
    """The JSON Schema of a kind of YAML file, for editors (shipped in configs/schemas/)."""
    from vslab.schemas import schema_text

    try:
        text = schema_text(name)
    except KeyError as exc:
        _error(exc.args[0])
    if out is None:
        typer.echo(text, nl=False)
        return
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        _error(f"cannot write {out}: {exc.strerror or exc}")
    if not options().quiet:
        console.print(f"written: {out}")


@twin_app.command("survey")
def twin_survey(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    trajectory: Annotated[
        str, typer.Option(help="Experiment 1 trajectory: linear, curve or square.")
    ] = "curve",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Experiment 1 on the twin: mean tip error (mm) per pressure × payload."""
    from twin.survey import experiment1_survey

    desc = _robot(robot)
    try:
        grid = experiment1_survey(desc, trajectory=trajectory, seed=seed)
    except ValueError as exc:
        _fail(str(exc))
    _print_grid(grid, f"{desc.name}: mean tip error (mm), true tip vs rigid FK of the encoders, {trajectory}")
    out = options().lab.twin.survey(desc.name, trajectory)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(grid.to_dict(), indent=2))
    if not options().quiet:
        console.print(f"written: {out}")


@app.command()
def rig(
    robot: Annotated[str, typer.Option(help="Robot description.")] = "vsl",
    run_dir: Annotated[Path | None, typer.Option(help="Where ports.json and the port links go.")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    factory: Annotated[
        bool,
        typer.Option("--factory", help="Every device as it comes out of the box (a lab's first session)."),
    ] = False,
) -> None:
    """Run the twin in real time behind emulators of the robot's devices (until Ctrl-C / SIGTERM)."""
    from acquisition.processes import RT_PRIORITY, elevate
    from twin.rig import serve_rig

    desc = _robot(robot)
    where = run_dir or local_lab("rig (without --run-dir)").rigs
    if not options().quiet:
        console.print(f"rig for {desc.name}: ports in {where / 'ports.json'} (Ctrl-C stops)")
    # as `python -m twin.rig`: the rig stands in for hardware, which a busy computer does not slow down
    elevate(fifo_priority=RT_PRIORITY + 1)
    serve_rig(desc, where, seed=seed, factory=factory)


@app.command()
def demo(
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    quick: Annotated[
        bool,
        typer.Option("--quick", help="A smaller campaign, fewer repetitions, 30 epochs at most a network."),
    ] = False,
) -> None:
    """The main job: the whole lab on the twin, end to end (rig session, simulated campaign and experiments,
    datasets, training, Experiment 2 with the trained inverse model, figures, report)."""
    import time

    from vslab import lab_job

    if seed < 0:
        _error(f"--seed must be ≥ 0, got {seed}")
    start = time.perf_counter()
    report = lab_job.run(
        local_lab("demo"),
        seed=seed,
        quick=quick,
        say=lambda m: console.print(m, highlight=False),
        batch_priority=True,
    )
    console.print(f"main job done in {time.perf_counter() - start:.0f} s; the report: {report.resolve()}")


@app.command()
def figures() -> None:
    """Regenerate every figure and table from the lab's newest datasets and models, and the report."""
    from rich.markup import escape

    from analysis.lab_figures import all_figures
    from analysis.lab_report import lab_report

    lab = options().lab
    datasets = lab.datasets.root
    if not any(datasets.glob("*/*/card.json")):
        _error(f"no datasets in {datasets}: nothing to draw (build some first: `vslab build`, `vslab demo`)")
    try:
        results = all_figures(lab)  # each failure is a `not made:` line below, with why
    except OSError as exc:  # the figures or report folder cannot be written
        _error(f"{exc.filename or lab}: cannot be written ({exc.strerror or exc})")
    for what, why in results.missing.items():
        console.print(f"[yellow]not made: {escape(what)}:[/] {escape(why)}", soft_wrap=True)
    console.print(f"{len(results.figures)} figures in {lab.figures}; "
                  f"report: {lab_report(lab, results).resolve()}")  # fmt: skip


@app.command()
def simulate(
    experiment: Annotated[str, typer.Argument(help="Experiment: experiment1, campaign, or a YAML path.")],
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override an experiment parameter: key=value (repeatable)."),
    ] = None,
    benches: Annotated[int, typer.Option(help="Twin benches stepped together (batch size).")] = 128,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    inverse_model: Annotated[
        str | None,
        typer.Option(help="Saved inverse model (version) for Experiment 2's hybrid commands."),
    ] = None,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Build and check the plans, print size and duration, stop.")
    ] = False,
    processes: Annotated[
        int | None,
        typer.Option(
            help="Worker processes the benches are spread over (default: one per core; the "
            "sessions are the same however many)."
        ),
    ] = None,
) -> None:
    """Run an experiment on the twin in simulated time: the same sessions as on the rig, much faster."""
    import time

    import numpy as np
    from rich.progress import Progress

    from acquisition.recorder.sessions import SessionStore
    from acquisition.safety import SafetyError
    from pipeline.in_loop import learned_compensators
    from twin.runner import SIM_PREFIX, prepare_experiment, simulate_experiment

    if benches < 1 or seed < 0:
        _error(f"--benches must be ≥ 1 and --seed ≥ 0, got --benches {benches} --seed {seed}")
    if processes is not None and processes < 1:
        _error(f"--processes must be ≥ 1, got {processes}")
    overrides = _overrides(set_ or [])
    if "history" in str(overrides.get("commands", "")):
        _error(HISTORY_NOT_STORED)
    model = None if inverse_model is None else load_inverse_model(inverse_model)  # checked before any run
    model_version = None if inverse_model is None else inverse_model_version(inverse_model)
    try:  # every argument checked before the batch priority (on a busy machine a typo is refused at once)
        prepared = prepare_experiment(experiment, overrides, benches, seed, model)
    except (ValueError, OSError, RobotDescriptionError, SafetyError) as exc:  # ExperimentError, a bad robot
        _error(str(exc))
    if dry_run:
        _, plans, _ = prepared
        points = sum(len(p.goal_t) + len(p.pressure_t) + len(p.payload_t) for p in plans)
        console.print(f"{experiment}: {len(plans)} plans, {points:,} set-points, "
                      f"{sum(p.duration_s for p in plans):,.0f} bench-seconds (dry run: nothing simulated)",
                      soft_wrap=True)  # fmt: skip
        return
    from acquisition.processes import lower_priority

    lower_priority()  # batch work: a recording on this computer goes first
    start = time.perf_counter()
    sessions = options().lab.sessions
    sessions_dir = sessions.root
    compensators = []
    learned = learned_compensators({"hybrid": model}, identities={"hybrid": model_version})

    def hybrid(plan):
        compensators.append(learned(plan))
        return compensators[-1]

    with Progress(console=console, disable=options().quiet, transient=True) as bar:
        tasks: dict[str, int] = {}

        def progress(label: str, fraction: float) -> None:
            if label not in tasks:
                tasks[label] = bar.add_task(label, total=1.0)
            bar.update(tasks[label], completed=fraction)

        folder = sessions_dir
        try:
            # on a store, the sessions are written locally and uploaded once whole
            with sessions.staged(f"{SIM_PREFIX}*") as folder:
                reports = simulate_experiment(
                    experiment, SessionStore(folder), seed=seed, benches=benches, overrides=overrides,
                    progress=progress, inverse_model=hybrid if model is not None else None, prepared=prepared,
                    processes=processes or os.cpu_count() or 1,
                )  # fmt: skip
        except (ValueError, OSError, RobotDescriptionError, SafetyError) as exc:  # ExperimentError, full disk
            bar.stop()
            _error(str(exc).replace(str(folder), str(sessions_dir)))  # a store's sessions by their own path
    wall = time.perf_counter() - start
    written = sum(len(r.sessions) for r in reports)
    skipped = sum(len(r.skipped) for r in reports)
    simulated = sum(r.simulated_s for r in reports)
    messages = sum(r.messages for r in reports)
    console.print(
        f"{experiment}: {written} sessions written, {skipped} already complete; "
        f"{simulated:,.0f} bench-seconds simulated in {wall:.1f} s ({simulated / wall:,.0f}× real time), "
        f"{messages:,} messages → {sessions_dir}"
    )
    latencies = [t * 1e6 for c in compensators for t in c.latencies_s]
    if latencies:
        p50, p99 = np.percentile(latencies, [50, 99])
        console.print(
            f"inverse model in the loop: {len(latencies)} set-points, {p50:.0f} µs p50, {p99:.0f} µs p99"
        )
    stopped = {sid: why for r in reports for sid, why in r.stopped.items()}
    for sid, why in sorted(stopped.items())[:10]:
        console.print(f"  {sid} stopped early: {why}", soft_wrap=True, highlight=False, markup=False)
    if stopped:
        _error(f"{len(stopped)} session(s) stopped early (a safety limit or a refused command; their events "
               "say why): they ran only up to the stop")  # fmt: skip


@app.command()
def build(
    name: Annotated[str, typer.Option(help="Dataset name (datasets/<name>/<version>/).")] = "campaign",
    experiment: Annotated[
        str | None,
        typer.Option(
            "--experiment",
            "--protocol",  # its former name, kept so a lab's scripts go on working
            help="Only sessions of this experiment (default: the dataset name's).",
        ),
    ] = None,
    pattern: Annotated[str, typer.Option("--sessions", help="Session directories to consider (glob).")] = "*",
    set_: Annotated[
        list[str] | None, typer.Option("--set", help="A stage parameter: stage.key=value (repeatable).")
    ] = None,
    workers: Annotated[int, typer.Option(help="Parallel processes (0: one per core).")] = 0,
    cluster: Annotated[
        str | None,
        typer.Option(
            help="A Dask scheduler (tcp://host:port) whose workers process the sessions; they must see the "
            "lab at the same path, or the same store (vslab[cluster])."
        ),
    ] = None,
) -> None:
    """Build a versioned dataset from recorded sessions: ingest, clean, sync, registration, segment, D,
    splits.
    Every stage is cached: building again with nothing changed does no work. A session that cannot be read
    (a damaged session.json or MCAP part, a folder without session.json) gets a `warning:` line with its
    reason and is left out; the others build (exit 0). No usable session: one `error:` line, exit 2."""
    import concurrent.futures as cf
    import time
    from concurrent.futures.process import BrokenProcessPool

    from rich.markup import escape
    from rich.progress import Progress

    from pipeline.build import BuildError
    from pipeline.build import build as build_dataset
    from pipeline.cluster import ClusterError, cluster_executor

    parameters = _stage_parameters(set_ or [])
    wanted = experiment or name
    sessions, bad = _sessions_of(wanted, pattern)

    def warn(skipped: dict[str, str]) -> None:
        for session, reason in sorted(skipped.items()):
            console.print(f"[yellow]warning:[/] skipped {escape(session)}: {escape(reason)}", soft_wrap=True,
                          highlight=False)  # fmt: skip

    if not sessions:
        warn(bad)
        unusable = f" ({len(bad)} folder(s) skipped, see above)" if bad else ""
        _fail(escape(f"no usable session of experiment {wanted!r} in {options().lab.sessions.root}{unusable} "
                     "(see `vslab sessions list`)"))  # fmt: skip
    if cluster is not None and workers:
        _fail("--workers and --cluster: the cluster's workers build (give one of them)")
    from acquisition.processes import lower_priority

    lower_priority()  # arguments checked; batch work: a recording on this computer goes first
    start = time.perf_counter()
    with (
        contextlib.ExitStack() as stack,
        Progress(console=console, disable=options().quiet, transient=True) as bar,
    ):
        task = bar.add_task(f"{len(sessions)} sessions", total=len(sessions))
        try:
            executor = None
            if cluster is not None:
                executor = stack.enter_context(cluster_executor(cluster))
            elif workers > 0:
                executor = stack.enter_context(cf.ProcessPoolExecutor(workers))
            report = build_dataset(sessions, options().lab, name, parameters, executor=executor,
                                   progress=lambda done, total: bar.update(task, completed=done))  # fmt: skip
        except BuildError as exc:
            bar.stop()
            warn(bad | exc.failed)
            _fail(escape(str(exc)))
        except (ValueError, OSError, ClusterError) as exc:
            bar.stop()
            warn(bad)
            _fail(escape(str(exc)))
        except BrokenProcessPool:
            bar.stop()
            _fail("a build worker process died (out of memory?): try fewer --workers")
    wall = time.perf_counter() - start
    what = "built" if report.built else "already built (nothing to do)"
    inputs = f"{len(report.sessions)} sessions ({report.cached} cached)"
    line = f"dataset {name} {report.version}: {what}, {report.rows:,} rows from {inputs} in {wall:.1f} s"
    console.print(line, soft_wrap=True)
    console.print(f"  → {report.path}", soft_wrap=True, highlight=False, markup=False)
    for session, lines in sorted(report.damaged.items()):  # its other chunks built; these messages are lost
        for text in lines:
            console.print(f"[yellow]warning:[/] {escape(session)}: {escape(text)}", soft_wrap=True,
                          highlight=False)  # fmt: skip
    warn(bad | report.failed)


# a stage's former name → its name now: `--set register.from_dataset=…` (the README's command before the
# frame registration's stage was named for what it is) is read as `registration.from_dataset=…`, warned
RENAMED_STAGES = {"register": "registration"}


def _stage_parameters(pairs: list[str]) -> dict:
    """``--set stage.key=value`` pairs → {stage: {key: value}}, checked against the stages' parameters (one
    error line naming a bad key or value and the allowed ones)."""
    from rich.markup import escape

    from pipeline.build import check_parameters, stage_parameters

    parameters: dict = {}
    for key, value in _overrides(pairs).items():  # a value that is not YAML: one line from _overrides
        stage, dot, param = key.partition(".")
        if not (dot and stage and param):
            _fail(escape(f"--set {key}=…: a stage parameter is stage.key=value (stages: "
                         f"{', '.join(stage_parameters())})"))  # fmt: skip
        if stage in RENAMED_STAGES:  # commands written before the rename still build the same dataset
            new = RENAMED_STAGES[stage]
            console.print(f"[yellow]warning:[/] --set {escape(key)}: the stage {stage!r} is now {new!r}; "
                          "the old name will go", highlight=False, soft_wrap=True)  # fmt: skip
            stage = new
        parameters.setdefault(stage, {})[param] = value
    try:
        check_parameters(parameters)
    except ValueError as exc:
        _fail(escape(f"--set {exc}"))
    return parameters


def _sessions_of(wanted: str, pattern: str) -> tuple[list[Path], dict[str, str]]:
    """The session folders of experiment ``wanted`` ("all": every one) matching ``pattern``, and the folders
    that are not readable sessions with the reason (a folder without session.json never joins a build)."""
    from rich.markup import escape

    sessions = options().lab.sessions
    root = sessions.root
    if not root.is_dir():
        _fail(escape(f"no sessions folder at {root}: record or simulate sessions first (`vslab simulate`)"))
    try:
        return sessions.select(wanted, pattern=pattern)
    except (OSError, ValueError) as exc:
        _fail(escape(f"--sessions {pattern!r}: cannot list {root} ({exc})"))


def _print_grid(grid, title: str) -> None:
    if options().quiet:
        return
    table = Table(title=title)
    table.add_column("pressure")
    for col in grid.columns:
        table.add_column(str(col), justify="right")
    for idx, row in grid.iterrows():
        table.add_row(str(idx), *(f"{v:.2f}" for v in row))
    console.print(table)


if __name__ == "__main__":  # pragma: no cover
    app(prog_name=os.path.basename(__file__))
