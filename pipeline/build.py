"""`vslab build`: sessions → versioned dataset, every step cached, sessions processed in parallel.

Two levels of work:
1. per session (independent, parallel): ingest → clean → sync → segment, cached under
   ``<lab>/cache/session/<key>/`` by the session's content hash + the stages' parameters + the code version;
2. per robot (needs every session): register the tracker frame to the robot base from the static points of
   all its sessions, put every tip position in the base frame, assemble D, split, and write the dataset under
   a version that is the hash of all of its inputs: a build with nothing changed finds it and does no work.

Parallel work goes through any ``concurrent.futures.Executor``: local processes by default; a distributed
engine's executor (Dask's ``Client.get_executor()``, Ray's) runs the same top-level function on many machines
(the cache directory must then be shared storage). A session that fails (torn beyond reading, not MCAP, empty)
is reported with its reason in the card; the others still build.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from models.robot import RobotDescription
from pipeline import datasets
from pipeline.cache import StageCache, code_version, stage_key
from pipeline.tables import columns

log = logging.getLogger(__name__)

DEFAULTS: dict = {
    "clean": {"hampel_window": 7, "hampel_sigmas": 4.0},
    "segment": {},
    "register": {},
    "splits": {"seed": 0, "group": "session"},
}


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


def process_session(directory: str, parameters: dict, cache_root: str) -> dict:
    """Per-session stages of one session (a top-level function: any executor can run it). Returns a small
    record: the cache key of its outputs, or the reason it failed."""
    from pipeline.clean import clean
    from pipeline.ingest import ingest_session, session_parts, source_hash
    from pipeline.segment import Stillness, repetitions, static_points
    from pipeline.sync import sync

    directory = Path(directory)
    cache = StageCache(Path(cache_root))
    try:
        parts = session_parts(directory)
        if not parts:
            raise ValueError(f"{directory}: no MCAP parts")
        source = source_hash(parts)
        session_params = {k: parameters[k] for k in ("clean", "segment")}
        key = stage_key("session", [source], session_params)
        if cache.has("session", key):
            return {"session": directory.name, "key": key, "source": source, "cached": True}
        s = ingest_session(directory)
        s = clean(s, **parameters["clean"])
        s, timeline = sync(s)
        still = Stillness(**parameters["segment"])
        points = static_points(timeline, s.events, s.t0_ns, stillness=still, report=s.report)
        timeline = timeline.assign(repetition=repetitions(timeline, s.events, s.t0_ns))
        trajectory = timeline[timeline["repetition"] >= 0]
        record = {"session": directory.name, "robot": s.robot.name, "source": source,
                  "robot_description": s.robot.model_dump_json(), "report": s.report.as_dict(),
                  "metadata": {k: v for k, v in s.metadata.items() if k != "robot_description"}}  # fmt: skip
        cache.store("session", key, {"static": points, "trajectory": trajectory}, record)
        return {"session": directory.name, "key": key, "source": source, "cached": False}
    except Exception as exc:  # one bad session must not stop the build; its reason goes in the card
        log.warning("session %s: %s", directory.name, exc)
        return {"session": directory.name, "error": f"{type(exc).__name__}: {exc}"}


def build(
    sessions: list[Path],
    lab: Path,
    name: str,
    parameters: dict | None = None,
    executor: cf.Executor | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> BuildReport:
    """Build dataset ``name`` from ``sessions`` into ``<lab>/datasets`` (stage outputs in ``<lab>/cache``)."""
    params = {k: {**DEFAULTS[k], **(parameters or {}).get(k, {})} for k in DEFAULTS}
    if "from_dataset" in params["register"]:  # pin the borrowed registration's version: part of ours
        params["register"]["from_dataset"] = _resolve(
            Path(lab) / "datasets", params["register"]["from_dataset"]
        )
    cache_root = Path(lab) / "cache"
    own = executor is None
    if own:
        workers = max(1, min(len(sessions), os.cpu_count() or 1))
        executor = cf.ProcessPoolExecutor(workers) if workers > 1 else InlineExecutor()
    try:
        futures = [executor.submit(process_session, str(d), params, str(cache_root)) for d in sessions]
        results = []
        for k, future in enumerate(cf.as_completed(futures)):
            results.append(future.result())
            if progress:
                progress(k + 1, len(futures))
    finally:
        if own:
            executor.shutdown()
    results.sort(key=lambda r: r["session"])
    good = [r for r in results if "error" not in r]
    failed = {r["session"]: r["error"] for r in results if "error" in r}
    sources = {r["session"]: r["source"] for r in good}
    version = datasets.dataset_version(sources, params)
    root = Path(lab) / "datasets"
    report = BuildReport(name, version, root / name / version, False, sorted(sources), failed,
                         sum(bool(r.get("cached")) for r in good))  # fmt: skip
    if (report.path / "card.json").is_file():
        report.rows = int(pd.read_parquet(report.path / "data.parquet", columns=["robot"]).shape[0])
        return report
    if not good:
        raise ValueError(f"no session could be read: {failed}")
    cache = StageCache(cache_root)
    loaded = [(r, *cache.load("session", r["key"])) for r in good]
    tables, card_sessions, registrations = {"data": [], "trajectories": []}, {}, {}
    for robot_name in sorted({rec["robot"] for _, _, rec in loaded}):
        mine = [(r, t, rec) for r, t, rec in loaded if rec["robot"] == robot_name]
        robot = RobotDescription.model_validate_json(mine[0][2]["robot_description"])
        static = _tagged([(rec, t["static"]) for _, t, rec in mine])
        trajectory = _tagged([(rec, t["trajectory"]) for _, t, rec in mine])
        registration = _register(static, robot, params["register"], Path(lab) / "datasets")
        registrations[robot_name] = registration
        for table, rows in (("data", static), ("trajectories", trajectory)):
            if len(rows):
                tables[table].append(datasets.assemble(_in_base_frame(rows, registration), robot))
        card_sessions |= {rec["session"]: _session_card(rec) for _, _, rec in mine}
    trajectories = pd.concat(tables["trajectories"], ignore_index=True) if tables["trajectories"] else None
    # D is the static points; sessions of trajectories only (Experiment 1/2) give D of their samples
    rows = tables["data"] or ([trajectories] if trajectories is not None else [])
    if not rows:
        raise ValueError("the sessions have neither settled points nor trajectory repetitions")
    data = datasets.add_splits(pd.concat(rows, ignore_index=True), **params["splits"])
    out = {"data": data} | ({"trajectories": trajectories} if trajectories is not None else {})
    card = {
        "sources": sources, "failed": failed, "parameters": params, "code_version": code_version(),
        "sessions": card_sessions,
        "registration": {k: _registration_card(v) for k, v in registrations.items()},
    }  # fmt: skip
    datasets.write_dataset(root, name, version, out, card)
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


def _register(static: pd.DataFrame, robot: RobotDescription, parameters: dict, datasets_root: Path):
    """Fit tracker → base on these sessions' static points, or take it from another dataset of the same
    setup (``from_dataset: name@version``: trajectory-only sessions such as Experiment 2 have no static
    points)."""
    from pipeline.register import FixedRegistration, register

    if "from_dataset" not in parameters and not len(static):
        raise ValueError(
            f"no settled static points of {robot.name} to register the tracker on: take the registration of "
            "another dataset of the same setup (--set register.from_dataset=campaign)"
        )
    if "from_dataset" in parameters:
        name, _, version = parameters["from_dataset"].partition("@")
        _, card = datasets.load_dataset(datasets_root, name, version, table=None)
        fitted = card.get("registration", {})
        # an arm on the same mount (the rigid-link arm in place of the VSL arm) shares the tracker placement
        mine = fitted.get(robot.name) or (next(iter(fitted.values())) if len(fitted) == 1 else None)
        if mine is None:
            raise ValueError(f"dataset {name}@{version} has no registration for robot {robot.name!r}")
        return FixedRegistration.from_summary(mine, source=parameters["from_dataset"])
    return register(static, robot, **parameters)


def _resolve(root: Path, reference: str) -> str:
    """``name`` or ``name@version`` → ``name@version`` (the newest version when none is named)."""
    name, _, version = reference.partition("@")
    _, card = datasets.load_dataset(root, name, version or None, table=None)
    return f"{name}@{card['version']}"


def _in_base_frame(rows: pd.DataFrame, registration) -> pd.DataFrame:
    """``x_0..2``: the tracker positions mapped into the robot base frame by the fitted registration."""
    x = registration.to_base(columns(rows, "tracker_position"))
    return rows.assign(**{f"x_{k}": x[:, k] for k in range(3)})


def _session_card(record: dict) -> dict:
    report = record["report"]
    return {"source": record["source"], "removed": report["removed"], "warnings": report["warnings"],
            "values": report["values"], "protocol": record["metadata"].get("protocol", "")}  # fmt: skip


def _registration_card(registration) -> dict:
    return registration.summary() if hasattr(registration, "summary") else repr(registration)


class InlineExecutor(cf.Executor):
    """One worker: run in this process (no pool to start for a single session or a single core)."""

    def submit(self, fn, /, *args, **kwargs):
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            future.set_exception(exc)
        return future
