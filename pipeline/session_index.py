"""The sessions of one experiment for the pipeline and the figures: ``SessionStore.select`` with each damaged
folder named in the log (never joined), and the error a damaged session raises, for the layers above."""

from __future__ import annotations

import logging
from pathlib import Path

from acquisition.recorder.sessions import SessionStore
from acquisition.schemas.session_files import SessionError

__all__ = ["SessionError", "sessions_of"]

log = logging.getLogger(__name__)


def sessions_of(sessions: SessionStore, experiment: str, runner: str | None = None) -> list[Path]:
    """The session folders of one experiment in ``sessions``, of one runner ("simulated", "real-time") if
    given; a damaged folder is named in the log and never joins a dataset."""
    selected, bad = sessions.select(experiment, runner)
    for why in bad.values():
        log.warning("skipped %s", why)
    return selected
