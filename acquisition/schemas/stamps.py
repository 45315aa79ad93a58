"""Device stamps in the session payloads are wrapping counters (the servo's Realtime Tick wraps at 32768 ms,
the boards' micros() and the tracker's frame number at 2³²): undoing the wraps, for whoever reads them."""

from __future__ import annotations

import numpy as np


def unwrap_ticks(ticks: np.ndarray, wrap: int) -> np.ndarray:
    """Undo counter wraps in a 1-D sequence of wrapped ticks (int64 out, starting at ticks[0]).

    Assumes consecutive samples are less than half a wrap apart (a longer gap is ambiguous and is read as the
    shorter way round); a backward jump of more than half a wrap is taken as one wrap forward.
    """
    ticks = np.asarray(ticks, dtype=np.int64)
    if ticks.ndim != 1:
        raise ValueError(f"unwrap_ticks takes a 1-D sequence, got shape {ticks.shape}")
    step = np.diff(ticks)
    turns = np.cumsum((step < -(wrap // 2)).astype(np.int64) - (step > wrap // 2))
    return ticks + np.concatenate([np.zeros(min(ticks.size, 1), np.int64), turns]) * np.int64(wrap)
