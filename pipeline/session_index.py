"""Which sessions a lab holds: the one place the pipeline and the figures choose sessions by experiment and
runner, from each folder's ``session.json`` (a damaged folder is named with its reason, never joined)."""

from __future__ import annotations

import logging
from pathlib import Path

from acquisition.recorder.sessions import SessionStore
from acquisition.schemas.session_files import SessionError, SessionInfo, read_card, session_info

__all__ = ["SessionError", "experiment_sessions", "read_session", "sessions_of"]

log = logging.getLogger(__name__)


def experiment_sessions(
    root: Path, experiment: str, runner: str | None = None, pattern: str = "*"
) -> tuple[list[Path], dict[str, str]]:
    """The session folders under ``root`` (a lab's ``sessions/``) matching ``pattern`` of ``experiment``
    ("all": every one), of ``runner`` ("simulated", "real-time") if given, in name order; and the folders
    that are not readable sessions, each with why (:meth:`SessionStore.select`)."""
    return SessionStore(root).select(experiment, runner, pattern)


def read_session(directory: Path) -> tuple[dict, SessionInfo]:
    """(card, what its parts hold) of one session; ``SessionError`` for a damaged one."""
    return read_card(directory), session_info(directory)


def sessions_of(sessions: SessionStore, experiment: str, runner: str | None = None) -> list[Path]:
    """The session folders of one experiment in ``sessions``, of one runner ("simulated", "real-time") if
    given; a damaged folder is named in the log and never joins a dataset."""
    selected, bad = sessions.select(experiment, runner)
    for why in bad.values():
        log.warning("skipped %s", why)
    return selected
