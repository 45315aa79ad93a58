"""A history-aware model: what the arm did before a static point, as features beside what is measured at it.

The networks and the other baselines see a point's measured joints, pressures and currents only. An arm with
creep or hysteresis ends each point where its load history put it, so the same measurements can mean
different tips. This model also reads, per input column, the values at the session's previous points (the
``lags`` last ones) and their exponentially weighted means over ``time_constants_s`` (the slow memory creep
has), with the time since the previous point. Those are inputs only — never a measured tip — computed over
the whole session in time order, so a point's history is the same whichever split it falls in.

``with_history(D)`` adds the ``hist_*`` columns to the full dataset (before any split: a split's test part
alone would lose its points' predecessors); :class:`HistoryModel` is gradient boosting on the residual, like
the ``gbr`` baseline, with those columns beside the 7 inputs.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from models.hybrid import FORWARD_INPUTS, INVERSE_INPUTS
from pipeline.baselines import SklearnBaseline

LAGS = 2
TIME_CONSTANTS_S = (10.0, 60.0)
PREFIX = "hist_"


SOURCES = tuple(dict.fromkeys([*FORWARD_INPUTS, *INVERSE_INPUTS]))  # every input column, forward and inverse


def history_columns(lags: int = LAGS, time_constants_s: tuple[float, ...] = TIME_CONSTANTS_S,
                    sources: tuple[str, ...] = SOURCES) -> list[str]:  # fmt: skip
    """The names :func:`with_history` adds for ``sources`` (by default all it adds), in order."""
    names = [f"{PREFIX}dt_s"]
    for c in sources:
        names += [f"{PREFIX}{c}_step"]
        names += [f"{PREFIX}{c}_lag{k}" for k in range(1, lags + 1)]
        names += [f"{PREFIX}{c}_ewm{tau:g}s" for tau in time_constants_s]
    return names


def with_history(d: pd.DataFrame, lags: int = LAGS,
                 time_constants_s: tuple[float, ...] = TIME_CONSTANTS_S) -> pd.DataFrame:  # fmt: skip
    """``d`` with the ``hist_*`` columns: per session in time order, for every forward and inverse input
    column, the move into the point (its value minus the previous point's: which side the joints came from),
    its value ``k`` points before (k = 1 … ``lags``; the first point's own value where there is none)
    and its exponentially weighted mean over the points before (weight e^(−Δt/τ) per second of age; the first
    point's own value to start), and ``hist_dt_s``, the seconds since the previous point (0 for the first)."""
    sources = list(SOURCES)
    sessions, times, values = d["session"].to_numpy(), d["t"].to_numpy(float), d[sources].to_numpy(float)
    out = np.empty((len(d), len(history_columns(lags, time_constants_s))))
    for session in pd.unique(sessions):
        at = np.flatnonzero(sessions == session)
        at = at[np.argsort(times[at], kind="stable")]
        x, dt = values[at], np.diff(times[at], prepend=times[at[0]])
        lagged = [np.concatenate([np.repeat(x[:1], min(k, len(x)), axis=0), x[:-k]])[: len(x)]
                  for k in range(1, lags + 1)]  # fmt: skip
        means = []
        for tau in time_constants_s:
            ewm = np.empty_like(x)
            ewm[0] = x[0]
            for j in range(1, len(x)):
                w = np.exp(-dt[j] / tau)
                ewm[j] = w * ewm[j - 1] + (1 - w) * x[j - 1]
            means.append(ewm)
        step = x - lagged[0] if lags else np.zeros_like(x)  # the move into the point (0 for the first)
        per_column = [np.column_stack([step[:, c], *(a[:, c] for a in lagged), *(m[:, c] for m in means)])
                      for c in range(len(sources))]  # fmt: skip
        out[at] = np.hstack([dt[:, None], *per_column])
    return d.assign(**dict(zip(history_columns(lags, time_constants_s), out.T, strict=True)))


class HistoryModel(SklearnBaseline):
    """Gradient boosting on the residual of the rigid model (as ``gbr``) from the 7 inputs and the point's
    history (``with_history``'s columns, which the rows must carry)."""

    def __init__(self, direction: str = "forward", random_state: int = 0, max_iter: int = 300) -> None:
        super().__init__("gbr", direction, random_state=random_state, max_iter=max_iter)

    @property
    def name(self) -> str:
        return "history"

    def _features(self, df: pd.DataFrame) -> np.ndarray:
        # the history of its own direction's inputs (an inverse input, the rigid IK, is NaN out of reach)
        names = history_columns(sources=tuple(c for c in SOURCES if c in self.inputs))
        if missing := [c for c in names if c not in df]:
            raise ValueError(
                f"HistoryModel needs the history columns of pipeline.history.with_history (missing "
                f"{missing[0]!r} and {len(missing) - 1} more): add them to the whole dataset before splitting"
            )
        return np.hstack([super()._features(df), df[names].to_numpy(float)])
