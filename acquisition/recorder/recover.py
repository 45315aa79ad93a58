"""Recover a torn MCAP part (writer killed: no summary, maybe half a chunk) into a new, valid, indexed file.

The original is never touched (raw sessions are immutable). The records are walked linearly until the first
one that is cut off or corrupt; every schema, channel, metadata record and message before it is written again
into a new file with a summary and indexes (``acquisition.schemas.mcap_writer.copy_readable``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from acquisition.schemas.mcap_writer import copy_readable
from acquisition.schemas.session_card import RECOVERED_SUFFIX, recovered_path

__all__ = ["RECOVERED_SUFFIX", "RecoveryReport", "recover", "recovered_path"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecoveryReport:
    source: Path
    output: Path
    messages: int
    channels: int
    torn: bool  # the source ended before its footer
    reason: str  # what stopped the walk ("" for a complete file)


def recover(source: str | Path, output: str | Path | None = None) -> RecoveryReport:
    """Write every readable record of ``source`` into ``output`` (default ``<name>.recovered.mcap``)."""
    source = Path(source)
    output = recovered_path(source) if output is None else Path(output)
    if output.resolve() == source.resolve() or (output.exists() and os.path.samefile(output, source)):
        raise ValueError("recovery writes a new file; it never overwrites the original")
    partial = output.with_name(f".{output.name}.partial")  # renamed into place whole: never a half file
    try:
        with open(source, "rb") as f, open(partial, "wb") as out:
            messages, channels, torn, reason = copy_readable(f, out, library="vslab recover")
        os.replace(partial, output)
    finally:
        partial.unlink(missing_ok=True)
    if torn:
        log.warning("%s: torn after %d messages (%s); recovered to %s", source, messages, reason, output)
    return RecoveryReport(source, output, messages, channels, torn, reason if torn else "")
