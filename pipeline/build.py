"""`vslab build`: sessions → versioned dataset, every step cached, sessions processed in parallel.

Two levels of work:
1. per session (independent, parallel): ingest → clean → sync → segment, cached under
   ``<lab>/cache/session/<key>/`` by the session's content hash + the stages' parameters + the code version;
2. per robot (needs every session): fit the registration (tracker frame → robot base) on the static points of
   all its sessions, put every tip position in the base frame, assemble D, split, and write the dataset under
   a version that is the hash of all of its inputs: a build with nothing changed finds it and does no work.

Parallel work goes through any ``concurrent.futures.Executor``: local processes by default; a distributed
engine's executor (Dask's ``Client.get_executor()``, Ray's) runs the same top-level function on many machines
(the cache directory must then be shared storage). A session that fails (torn beyond reading, not MCAP, empty)
is reported with its reason in the card; the others still build. When none can be read, ``BuildError`` says
so and nothing is written. Stage parameters are checked first: an unknown stage or key, or a value of the
wrong type, is a ``ValueError`` naming it and the allowed ones.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import inspect
import json
import logging
import os
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from acquisition.storage import LabPath, fetched, read_parquet
from models.robot import RobotDescription
from pipeline import datasets
from pipeline.cache import RECORD, StageCache, stage_key, stage_version
from pipeline.dataset_store import DatasetError
from pipeline.errors import PipelineError
from pipeline.tables import columns

if typing.TYPE_CHECKING:
    from pipeline.lab import DatasetStore, Lab
    from pipeline.registration import Registration

log = logging.getLogger(__name__)

DEFAULTS: dict = {
    "clean": {"hampel_window": 7, "hampel_sigmas": 4.0},
    "segment": {},
    "registration": {},
    "splits": {"seed": 0, "group": "session"},
}


# what a dataset's moves are made of (``pipeline.datasets.move_rows``): the cache keeps no more of them
MOVED = ("tracker_position_", "servo_position_", "stepper_position_", "pressure_")
LOADERS = 8  # threads reading the sessions' cached stage outputs for registration and D


class BuildError(PipelineError, ValueError):
    """No session of the build could be read: ``failed`` maps each session to its reason."""

    def __init__(self, failed: dict[str, str]) -> None:
        self.failed = dict(failed)
        reasons = set(failed.values())
        why = f": {reasons.pop()}" if len(reasons) == 1 else " (each session's reason is above)"
        super().__init__(f"none of the {len(failed)} session(s) could be read{why}")


def stage_parameters() -> dict[str, dict[str, object]]:
    """Every stage's parameters and their types, from the stage functions themselves (what ``--set
    stage.key=value`` may name): {stage: {key: type}}."""
    from pipeline import clean, registration, segment

    def keyword(fn: Callable, skip: int) -> dict[str, object]:
        hints = typing.get_type_hints(fn)
        names = list(inspect.signature(fn).parameters)[skip:]
        return {n: hints.get(n, object) for n in names}

    still = typing.get_type_hints(segment.Stillness)
    return {
        "clean": keyword(clean.clean, 1),
        "segment": {f.name: still[f.name] for f in dataclasses.fields(segment.Stillness)},
        "registration": keyword(registration.TrackerRegistration.__init__, 2) | {"from_dataset": str},
        "splits": keyword(datasets.add_splits, 1),
    }


def check_parameters(parameters: dict) -> None:
    """``ValueError`` naming the first unknown stage, unknown key or value of the wrong type (and what is
    allowed) in ``{stage: {key: value}}``."""
    allowed = stage_parameters()
    if not isinstance(parameters, dict):
        raise ValueError(f"stage parameters must be a mapping stage → {{key: value}}, got {parameters!r}")
    for stage, values in parameters.items():
        if stage not in allowed:
            raise ValueError(f"unknown stage {stage!r} (stage parameters are stage.key=value; stages: "
                             f"{', '.join(allowed)})")  # fmt: skip
        if not isinstance(values, dict):
            raise ValueError(f"stage {stage!r}: parameters must be key=value pairs, got {values!r}")
        for key, value in values.items():
            if key not in allowed[stage]:
                raise ValueError(f"{stage}.{key}: no such parameter (those of {stage}: "
                                 f"{', '.join(allowed[stage]) or 'none'})")  # fmt: skip
            want = allowed[stage][key]
            if not _fits(value, want):
                raise ValueError(f"{stage}.{key}={value!r}: expected {_type_name(want)}")


def _fits(value: object, want: object) -> bool:
    """Is ``value`` (parsed from YAML) of type ``want`` (int, float, bool, str, or a union with None)?"""
    if isinstance(want, types.UnionType) or typing.get_origin(want) is typing.Union:
        return any(_fits(value, w) for w in typing.get_args(want))
    if want is type(None):
        return value is None
    if want is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if want is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return want is object or (isinstance(want, type) and isinstance(value, want))


def _type_name(want: object) -> str:
    if isinstance(want, types.UnionType) or typing.get_origin(want) is typing.Union:
        return " or ".join(_type_name(w) for w in typing.get_args(want))
    names = {int: "an integer", float: "a number", bool: "true or false", str: "a string", type(None): "null"}
    return names.get(want, getattr(want, "__name__", str(want)))


@dataclass
class BuildReport:
    name: str
    version: str
    path: Path
    built: bool  # False: this version already existed, nothing was done
    sessions: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # session → reason
    cached: int = 0  # sessions whose per-session stages were already cached
    rows: int = 0
    damaged: dict[str, list[str]] = field(default_factory=dict)  # session → its damaged chunks, one line each


def process_session(directory: LabPath, parameters: dict, cache: StageCache) -> dict:
    """Per-session stages of one session into ``cache`` (a top-level function: any executor can run it; its
    arguments pickle). Returns a small record: the cache key of its outputs, or the reason it failed. A
    session on a store is fetched once into a temporary folder and read there."""
    where = local = directory
    try:
        with fetched(where) as local:
            return _session_stages(local, parameters, cache)
    except Exception as exc:  # one bad session must not stop the build; its reason goes in the card
        log.debug("session %s failed", where.name, exc_info=True)  # the caller shows the reason
        return {"session": where.name, "error": _reason(exc).replace(str(local), str(where))}


def _session_stages(directory: Path, parameters: dict, cache: StageCache) -> dict:
    """ingest → clean → sync → segment of the local session ``directory``, cached by its content."""
    from acquisition.schemas import topics
    from acquisition.schemas.session_card import readable_parts
    from pipeline.clean import clean
    from pipeline.ingest import DAMAGED_CHUNKS, IngestError, content_hash, ingest_session
    from pipeline.segment import Stillness, move_windows, repetitions, static_points
    from pipeline.sync import sync

    parts = readable_parts(directory)
    if not parts:
        raise IngestError(directory, "no MCAP parts (*.mcap)")
    content = content_hash(parts)
    session_params = {k: parameters[k] for k in ("clean", "segment")}
    key = stage_key("session", [content], session_params)
    done = {"session": directory.name, "key": key, "content_hash": content}
    if cache.has("session", key):
        record = json.loads((cache.path("session", key) / RECORD).read_text())
        damaged = record["report"]["values"].get(DAMAGED_CHUNKS, [])
        return done | {"cached": True, "damaged": damaged}
    s = ingest_session(directory, content=content)
    s = clean(s, **parameters["clean"])
    s, timeline = sync(s)
    still = Stillness(**parameters["segment"])
    points = static_points(timeline, s.events, s.t0_ns, stillness=still, report=s.report)
    timeline = timeline.assign(repetition=repetitions(timeline, s.events, s.t0_ns))
    trajectory = timeline[timeline["repetition"] >= 0]
    goals = s.streams.get(topics.SERVO_GOAL)  # the moves into the points, where goals were recorded
    moves = (move_windows(timeline, s.events, s.t0_ns, goals["t"].to_numpy(float)) if len(points) and
             goals is not None and "t" in goals.columns else timeline.iloc[:0])  # fmt: skip
    moves = moves[[c for c in moves.columns if c.startswith(MOVED) or c in ("t", "point", "t_command")]]
    record = {"session": directory.name, "robot": s.robot.name, "content_hash": content,
              "robot_description": s.robot.model_dump_json(), "report": s.report.as_dict(),
              "metadata": {k: v for k, v in s.metadata.items() if k != "robot_description"}}  # fmt: skip
    cache.store("session", key, {"static": points, "trajectory": trajectory, "moves": moves}, record)
    damaged = s.report.values.get(DAMAGED_CHUNKS, [])
    return done | {"cached": False, "damaged": damaged}


def _reason(exc: BaseException) -> str:
    """One line: an IngestError says which file and why; anything else is prefixed with its type."""
    from pipeline.ingest import IngestError

    text = " ".join(str(exc).split("\n")[0].split()) or type(exc).__name__
    return text if isinstance(exc, IngestError) else f"{type(exc).__name__}: {text}"


def _load_stages(done: dict, where: LabPath, params: dict, cache: StageCache) -> tuple[dict, dict, dict]:
    """(``done``, tables, record) of a session's cached stages. An entry that cannot be read (a page whose
    checksum fails: the cache's disk changed it) is discarded and made again from the session, saying so;
    where that fails too, an ``OSError`` with the session's reason."""
    try:
        return (done, *cache.load("session", done["key"]))
    except (OSError, ValueError) as exc:
        log.warning("session %s: its cached stages cannot be read (%s); making them again", done["session"],
                    _reason(exc))  # fmt: skip
    cache.discard("session", done["key"])
    again = process_session(where, params, cache)
    if "error" in again:
        raise OSError(f"session {done['session']}: its cached stages could not be read, and making them "
                      f"again failed: {again['error']}")  # fmt: skip
    return (done, *cache.load("session", again["key"]))


def build(
    sessions: list[LabPath],
    lab: Lab,
    name: str,
    parameters: dict | None = None,
    executor: cf.Executor | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> BuildReport:
    """Build dataset ``name`` from ``sessions`` into ``lab.datasets`` (stage outputs in ``lab.cache``).
    ``ValueError`` for bad parameters or a registration to borrow that is not there; ``BuildError`` when no
    session can be read."""
    check_parameters(parameters or {})
    params = {k: {**DEFAULTS[k], **(parameters or {}).get(k, {})} for k in DEFAULTS}
    borrowed = None  # (name@version, its card's registrations): read once, its version pinned in ours
    if "from_dataset" in params["registration"]:
        borrowed = _borrowed(lab.datasets, params["registration"]["from_dataset"])
        params["registration"]["from_dataset"] = borrowed[0]
    cache = lab.cache
    for stage in ("session", "dataset"):  # the code read once, here: a pool's workers forked later inherit it
        stage_version(stage)
    own = executor is None
    if own:
        workers = max(1, min(len(sessions), os.cpu_count() or 1))
        executor = cf.ProcessPoolExecutor(workers) if workers > 1 else InlineExecutor()
    try:
        results = []  # in the order of ``sessions``, each as soon as it and those before it are done
        each = len(sessions)  # lists, not itertools.repeat: a Dask executor maps collections only
        for record in executor.map(process_session, sessions, [params] * each, [cache] * each):
            results.append(record)
            if progress:
                progress(len(results), len(sessions))
    finally:
        if own:
            executor.shutdown()
    results.sort(key=lambda r: r["session"])
    good = [r for r in results if "error" not in r]
    failed = {r["session"]: r["error"] for r in results if "error" in r}
    made_from = {r["session"]: r["content_hash"] for r in good}
    version = datasets.dataset_version(made_from, params)
    report = BuildReport(name, version, lab.datasets.path(name, version), False, sorted(made_from), failed,
                         sum(bool(r.get("cached")) for r in good))  # fmt: skip
    report.damaged = {r["session"]: r["damaged"] for r in good if r.get("damaged")}
    if lab.datasets.has(name, version):
        report.rows = int(read_parquet(report.path / "data.parquet", columns=["robot"]).shape[0])
        return report
    if not good:
        raise BuildError(failed)
    where = {s.name: s for s in sessions}
    with cf.ThreadPoolExecutor(LOADERS) as pool:  # a store answers many requests at once, not one by one
        loaded = list(pool.map(lambda r: _load_stages(r, where[r["session"]], params, cache), good))
    tables, card_sessions, registrations = {"data": [], "trajectories": [], "moves": []}, {}, {}
    for robot_name in sorted({rec["robot"] for _, _, rec in loaded}):
        mine = [(r, t, rec) for r, t, rec in loaded if rec["robot"] == robot_name]
        robot = RobotDescription.model_validate_json(mine[0][2]["robot_description"])
        static = _tagged([(rec, t["static"]) for _, t, rec in mine])
        trajectory = _tagged([(rec, t["trajectory"]) for _, t, rec in mine])
        moves = _tagged([(rec, t["moves"]) for _, t, rec in mine if "moves" in t])
        registration = _fit_registration(static, robot, params["registration"], borrowed)
        registrations[robot_name] = registration
        for table, rows in (("data", static), ("trajectories", trajectory), ("moves", moves)):
            if len(rows):
                shape = datasets.move_rows if table == "moves" else datasets.assemble
                tables[table].append(shape(_in_base_frame(rows, registration), robot))
        card_sessions |= {rec["session"]: _session_card(rec) for _, _, rec in mine}
    trajectories = pd.concat(tables["trajectories"], ignore_index=True) if tables["trajectories"] else None
    # D is the static points; sessions of trajectories only (Experiment 1/2) give D of their samples
    rows = tables["data"] or ([trajectories] if trajectories is not None else [])
    if not rows:
        raise ValueError("the sessions have neither settled points nor trajectory repetitions")
    data = datasets.add_splits(pd.concat(rows, ignore_index=True), **params["splits"])
    out = {"data": data} | ({"trajectories": trajectories} if trajectories is not None else {})
    if tables["moves"]:  # the moves into the settled points: their links' swings (pipeline.damping_fit)
        out["moves"] = pd.concat(tables["moves"], ignore_index=True)
    card = {
        "made_from": made_from, "failed": failed, "parameters": params,
        "code_version": stage_version("dataset"), "sessions": card_sessions,
        "registration": {k: _registration_card(v) for k, v in registrations.items()},
    }  # fmt: skip
    lab.datasets.write(name, version, out, card)
    report.built, report.rows = True, len(data)
    return report


def _tagged(items: list[tuple[dict, pd.DataFrame]]) -> pd.DataFrame:
    """Rows of many sessions, each tagged with its session id and the plan it ran."""
    frames = [
        df.assign(session=rec["session"], plan=rec["metadata"].get("plan", ""))
        for rec, df in items
        if len(df)
    ]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _fit_registration(
    static: pd.DataFrame, robot: RobotDescription, parameters: dict, borrowed: tuple[str, dict] | None
) -> Registration:
    """Fit tracker → base on these sessions' static points, or take it from another dataset of the same
    setup (``borrowed``: ``from_dataset``'s name@version and its card's registrations; trajectory-only
    sessions such as Experiment 2 have no static points)."""
    from pipeline.registration import (
        FixedRegistration,
        RegistrationError,
        TrackerRegistration,
        borrowed_placement,
    )

    if borrowed is None and not len(static):
        raise ValueError(
            f"no settled static points of {robot.name} to register the tracker on: take the registration of "
            "another dataset of the same setup (--set registration.from_dataset=campaign)"
        )
    if borrowed is not None:
        reference, fitted = borrowed
        try:
            placement = borrowed_placement(fitted, robot.name, reference)
        except RegistrationError as exc:
            raise DatasetError(f"registration.from_dataset={parameters['from_dataset']}: {exc}") from None
        return FixedRegistration(placement, reference).fit(static)
    return TrackerRegistration(robot, **parameters).fit(static)


def _borrowed(store: DatasetStore, reference: str) -> tuple[str, dict]:
    """``name`` or ``name@version`` of the dataset whose registration a build borrows → (``name@version``,
    its card's registrations); ``DatasetError`` that names the parameter, the dataset and what to do."""
    try:
        return store.registrations(reference)
    except DatasetError as exc:
        raise DatasetError(f"registration.from_dataset={reference}: {exc}") from None


def _in_base_frame(rows: pd.DataFrame, registration: Registration) -> pd.DataFrame:
    """``x_0..2``: the tracker positions mapped into the robot base frame by the fitted registration."""
    x = registration.to_base(columns(rows, "tracker_position"))
    return rows.assign(**{f"x_{k}": x[:, k] for k in range(3)})


def _session_card(record: dict) -> dict:
    report = record["report"]
    return {"content_hash": record["content_hash"], "removed": report["removed"],
            "warnings": report["warnings"], "values": report["values"],
            "experiment": record["metadata"].get("experiment", "")}  # fmt: skip


def _registration_card(registration: Registration) -> dict:
    return registration.summary()


class InlineExecutor(cf.Executor):
    """One worker: run in this process (no pool to start for a single session or a single core)."""

    def submit(self, fn, /, *args, **kwargs):
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            future.set_exception(exc)
        return future
