"""Which sessions a lab holds: the one place the pipeline and the figures choose sessions by experiment and
runner, from each folder's ``session.json`` (a damaged folder is named with its reason, never joined)."""

from __future__ import annotations

from pathlib import Path

from acquisition.schemas.session_card import SESSION_CARD
from acquisition.schemas.session_files import SessionError, SessionInfo, read_card, session_info
from acquisition.storage import lab_path, published

__all__ = ["SessionError", "experiment_sessions", "read_session"]


def experiment_sessions(
    root: Path, experiment: str, runner: str | None = None, pattern: str = "*"
) -> tuple[list[Path], dict[str, str]]:
    """The session folders under ``root`` matching ``pattern`` of ``experiment`` ("all": every one), of
    ``runner`` ("simulated", "real-time") if given, in name order; and the folders that are not readable
    sessions, each with why."""
    selected, bad = [], {}
    for d in sorted(lab_path(root).glob(pattern)):
        if not d.is_dir() or d.name.startswith(".") or not published(d, SESSION_CARD):
            continue  # not a folder; hidden; on a store, a session still being uploaded
        try:
            card = read_card(d)
        except SessionError as exc:
            bad[d.name] = str(exc)
            continue
        if (experiment == "all" or card["experiment"] == experiment) and runner in (None, card.get("runner")):
            selected.append(d)
    return selected, bad


def read_session(directory: Path) -> tuple[dict, SessionInfo]:
    """(card, what its parts hold) of one session; ``SessionError`` for a damaged one."""
    return read_card(directory), session_info(directory)
