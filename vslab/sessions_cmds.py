"""`vslab sessions`: the lab's recorded sessions listed, inspected, recovered (never changed in place) and
uploaded to a lab on a store."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Column, Table

from vslab.app import _fail, console, options, sessions_app


@sessions_app.command("list")
def sessions_list() -> None:
    """Sessions in the lab: robot, experiment, status, duration, streams, drops. A folder that is not a
    readable session is listed as bad, with a warning line saying why; the rest are listed as usual
    (exit 0)."""

    table = Table(Column("session", no_wrap=True), "robot", "experiment", "status", "duration s", "messages",
                  "lost", "dropped", "torn parts")  # fmt: skip
    sessions = options().lab.sessions
    try:
        infos = sessions.list()
    except OSError as exc:
        _fail(escape(f"{sessions.root}: cannot be listed ({exc.strerror or exc})"))
    for info in infos:
        if info.problem:
            table.add_row(escape(info.id), "?", "?", "[red]bad[/]", *["–"] * 5)
            continue
        table.add_row(
            *(escape(v) for v in (info.id, info.robot, info.experiment, info.status)),
            f"{info.duration_s:.1f}",
            f"{sum(s.messages for s in info.streams.values()):,}", f"{info.lost:,}", f"{info.dropped:,}",
            str(len(info.torn)),
        )  # fmt: skip
    console.print(table)
    for info in infos:
        if info.problem:
            console.print(f"[yellow]warning:[/] {escape(info.problem)}", soft_wrap=True, highlight=False)
        for text in info.damaged:  # its other chunks are read; these messages are lost to every reader
            console.print(f"[yellow]warning:[/] {escape(text)}", soft_wrap=True, highlight=False)


def _session_dir(session: str) -> Path:
    sessions = options().lab.sessions
    directory = Path(session) if Path(session).is_dir() else sessions.path(session)
    if not directory.is_dir():
        _fail(f"no session {session!r} in {sessions.root} (see `vslab sessions list`)")
    return directory


def _session_info(session: str):
    """The session's SessionInfo, or one error line (a folder that is not a readable session)."""

    from acquisition.recorder.sessions import SessionError, session_info

    try:
        return session_info(_session_dir(session))
    except SessionError as exc:
        _fail(escape(str(exc)))
    except OSError as exc:
        _fail(escape(f"{exc.filename or session}: cannot be read ({exc.strerror or exc})"))


@sessions_app.command("info")
def sessions_info(session: Annotated[str, typer.Argument(help="Session id or directory.")]) -> None:
    """One session's streams: messages, time span, rate, and the recorder's account (expected, lost in
    gaps, dropped)."""
    info = _session_info(session)
    table = Table(
        "topic", "messages", "duration s", "rate Hz", "expected", "lost", "gaps", "dropped",
        title=f"{info.id}: {info.robot}, {info.experiment}, {info.status}, {len(info.parts)} part(s)",
    )  # fmt: skip
    for s in info.streams.values():
        expected = "—" if s.expected is None else f"{s.expected:,}"
        table.add_row(s.topic, f"{s.messages:,}", f"{s.duration_s:.2f}", f"{s.rate_hz:.1f}", expected,
                      f"{s.lost:,}", str(s.gaps), f"{s.dropped:,}")  # fmt: skip
    console.print(table)
    for part in info.torn:
        console.print(f"[yellow]torn part[/yellow] {part.name}: run `vslab sessions recover {info.id}`")
    for text in info.damaged:
        console.print(f"[yellow]warning:[/] {escape(text)}", soft_wrap=True, highlight=False)


@sessions_app.command("recover")
def sessions_recover(session: Annotated[str, typer.Argument(help="Session id or directory.")]) -> None:
    """Write a valid, indexed copy of every torn part (the originals are never changed). A folder that is not
    a readable session is refused with one line; nothing is written."""

    from acquisition.recorder.recover import recover
    from acquisition.storage import is_local

    info = _session_info(session)
    torn = info.torn
    if torn and not is_local(torn[0]):  # never reached by an upload: torn sessions are not published
        _fail(escape(f"{torn[0]}: a torn part on a store; recover the local session, then upload it"))
    if not torn and not info.damaged:
        console.print("nothing to recover: every part is whole")
    for part in torn:
        try:
            r = recover(part)
        except OSError as exc:
            _fail(escape(f"{part}: cannot write its recovered copy ({exc.strerror or exc}); it is unchanged"))
        console.print(
            f"{r.source.name} → {r.output.name}: {r.messages:,} messages ({r.reason or 'complete'})",
            soft_wrap=True, highlight=False, markup=False,
        )  # fmt: skip
    if info.damaged:  # a whole part's chunk that fails its CRC: nothing can mend it; say so, never "whole"
        more = f" (and {len(info.damaged) - 1} more damaged chunk(s))" if len(info.damaged) > 1 else ""
        _fail(escape(f"{info.damaged[0]}{more}; recover mends torn parts only: these messages are lost"))


@sessions_app.command("upload")
def sessions_upload(
    folders: Annotated[list[Path], typer.Argument(help="Local session folders (a lab's sessions/<id>).")],
) -> None:
    """Publish local sessions into the lab on a store (--lab s3://…): each one's parts first, its
    session.json last, so no reader ever sees half a session. A session the lab holds already is left as it
    is. Every folder is checked first: one that is not a complete, readable session is refused with one
    line, and nothing is uploaded."""
    from acquisition.recorder.sessions import SessionError, check_publishable

    sessions = options().lab.sessions
    root = sessions.root
    if options().lab.is_local:
        _fail(escape(f"--lab {options().lab} is a local folder: upload publishes into a lab on a store "
                     "(--lab s3://bucket/prefix); copy folders into a local lab"))  # fmt: skip
    for folder in folders:
        if not folder.is_dir():
            _fail(escape(f"{folder}: no such session folder"))
        try:
            check_publishable(folder)
        except SessionError as exc:
            _fail(escape(str(exc)))
    for folder in folders:
        try:
            uploaded = sessions.publish(folder)
        except SessionError as exc:
            _fail(escape(str(exc)))
        except OSError as exc:
            _fail(escape(f"{folder}: the upload to {root} failed ({exc}); nothing of it is visible there"))
        what = "uploaded" if uploaded else "already in the lab (left as it is)"
        console.print(f"{folder.name}: {what}", soft_wrap=True, highlight=False, markup=False)


_FOXGLOVE_HELP = (
    "One MCAP file that opens ready-made in Foxglove: the session plus /tf, /joint_states, the tip's "
    "pose and the robot's URDF."
)
_OUT_HELP = (
    "The file to write (default: <lab>/exports/<session>.foxglove.mcap; ./<session>.foxglove.mcap for "
    "a lab on a store)."
)
_REGISTRATION_HELP = "DATASET[@VERSION] whose fitted tracker registration places the tracker in /tf_static."


@sessions_app.command("export")
def sessions_export(
    session: Annotated[str, typer.Argument(help="Session id or directory.")],
    foxglove: Annotated[bool, typer.Option("--foxglove", help=_FOXGLOVE_HELP)] = False,
    out: Annotated[Path | None, typer.Option(help=_OUT_HELP)] = None,
    registration: Annotated[str | None, typer.Option(help=_REGISTRATION_HELP)] = None,
    rate_hz: Annotated[float, typer.Option(help="/tf and /joint_states rate (Hz), 0 < rate ≤ 1000.")] = 50.0,
) -> None:
    """Write a session as one file for a viewer; the session itself is never changed."""
    from acquisition.recorder.foxglove_export import ExportError, check_rate, export_foxglove, session_robot
    from acquisition.recorder.sessions import SessionError
    from acquisition.schemas.cdr import SchemaError
    from pipeline.registration import borrowed_placement

    if not foxglove:
        _fail("say what to export: --foxglove (the one format there is)")
    try:
        check_rate(rate_hz)
    except ExportError as exc:
        _fail(escape(str(exc)))
    info = _session_info(session)
    placement = None
    if registration is not None:
        try:
            robot = session_robot(info.parts[0]).name
            where, fitted = options().lab.datasets.registrations(registration)
            placement = borrowed_placement(fitted, robot, where)
        except (SessionError, ValueError) as exc:
            _fail(escape(str(exc)))
    name = f"{info.id}.foxglove.mcap"  # beside the lab's sessions; here when the lab is on a store
    lab = options().lab
    target = out or (lab.exports / name if lab.is_local else Path(name))
    if target.is_dir():
        _fail(escape(f"--out {target}: a directory; give the file to write (e.g. {target / name})"))
    try:
        n = export_foxglove(info.directory, target, placement, rate_hz)
    except (SessionError, SchemaError) as exc:
        _fail(escape(str(exc)))
    except OSError as exc:
        _fail(escape(f"{exc.filename or target}: cannot be written ({exc.strerror or exc})"))
    if not options().quiet:
        console.print(f"written: {target} ({n:,} messages)", soft_wrap=True, highlight=False, markup=False)
