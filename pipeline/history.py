"""A history-aware model: what the arm did before a row, as features beside what is measured at it.

The networks and the other baselines see a row's measured joints, pressures and currents only. An arm with
creep or hysteresis ends each move where its history put it, and on a path it trails its commands, so the
same measurements can mean different tips. This model also reads, per input column, what came before the
row. Which history is a :class:`HistoryWindow`:

- ``STATIC_POINTS`` (the campaign): the values at the session's ``lags`` previous points, the move into the
  point (which side the joints came from), the seconds since the previous point, and exponentially weighted
  means over ``time_constants_s`` (the slow memory creep has);
- ``PATHS`` (a trajectory, Experiment 1 and 2): exponentially weighted means over time constants only. They
  are the same whether the values are rows of a 40 Hz recording or set-points a compensator sees ten times a
  second, which lags and steps are not; ``x − mean_τ`` is the path's velocity times τ.

Those are inputs only — never a measured tip. :class:`HistoryState` computes them one row at a time: the same
code runs over a recorded session (``with_history``: per session in time order, over the whole dataset before
any split, so a row's history is the same whichever split it falls in) and in the control loop
(``pipeline.in_loop``); a path's model learns from its rows' set-point ends (:func:`set_point_ends`).
:class:`HistoryModel` is gradient boosting on the residual of the rigid model, like
the ``gbr`` baseline, with its window's columns beside the 7 inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from models.hybrid import FORWARD_INPUTS, INVERSE_INPUTS
from pipeline.baselines import SklearnBaseline

PREFIX = "hist_"
HISTORY_INPUTS = tuple(
    dict.fromkeys([*FORWARD_INPUTS, *INVERSE_INPUTS])
)  # every input column, both directions


@dataclass(frozen=True)
class HistoryWindow:
    """Which history a row carries: ``lags`` previous rows (with the step into the row and the time since
    the previous one; none when 0) and exponentially weighted means over ``time_constants_s``."""

    lags: int = 2
    time_constants_s: tuple[float, ...] = (10.0, 60.0)

    def columns(self, inputs: tuple[str, ...] = HISTORY_INPUTS) -> list[str]:
        """The names :func:`with_history` adds for the columns ``inputs`` (by default all), in order."""
        names = [f"{PREFIX}dt_s"] if self.lags else []
        for c in inputs:
            if self.lags:
                names += [f"{PREFIX}{c}_step"]
                names += [f"{PREFIX}{c}_lag{k}" for k in range(1, self.lags + 1)]
            names += [f"{PREFIX}{c}_ewm{tau:g}s" for tau in self.time_constants_s]
        return names


STATIC_POINTS = HistoryWindow()  # the campaign's points, 2 to 3 s apart
PATHS = HistoryWindow(lags=0, time_constants_s=(0.25, 1.0, 4.0, 30.0))  # a path, whatever its sample rate


class HistoryState:
    """The history of one stream of rows (one session, or one control loop), updated a row at a time:
    ``update(t, x)`` gives the features of row ``x`` (n_inputs values) at ``t`` seconds from the rows before
    it, in :meth:`HistoryWindow.columns` order, then remembers it. The first row is its own history (its
    values for every lag and mean, a step and a dt of 0). A mean weighs each value by how long it was held
    (e^(−age/τ)): exact for set-points held between calls. A missing value (NaN: a tip out of the rigid IK's
    reach) has no step; the history holds the last value seen, and a column seen first later starts there."""

    def __init__(self, window: HistoryWindow, n_inputs: int) -> None:
        self.window = window
        self.taus = np.asarray(window.time_constants_s, float)[:, None]
        self.t: float | None = None
        self.prev = np.full(n_inputs, np.nan)
        self.lagged = np.full((window.lags, n_inputs), np.nan)
        self.means = np.full((len(window.time_constants_s), n_inputs), np.nan)

    def update(self, t: float, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        held = np.where(np.isnan(x), self.prev, x)  # what the history remembers of this row
        dt = 0.0 if self.t is None else float(t) - self.t
        if self.t is not None:
            w = np.exp(-max(dt, 0.0) / self.taus)
            self.means = w * self.means + (1.0 - w) * self.prev
        self.means = np.where(np.isnan(self.means), held, self.means)  # the first value seen starts it
        self.lagged = np.where(np.isnan(self.lagged), held, self.lagged)
        per_input = [self.means]
        if self.window.lags:
            per_input = [x - self.lagged[:1], self.lagged, self.means]
        features = np.vstack(per_input).T.ravel()  # input by input: step, lags, means
        if self.window.lags:
            features = np.r_[dt, features]
            self.lagged = np.vstack([held, self.lagged[:-1]])
        self.t, self.prev = float(t), held
        return features


def with_history(d: pd.DataFrame, window: HistoryWindow = STATIC_POINTS) -> pd.DataFrame:
    """``d`` with ``window``'s ``hist_*`` columns for every forward and inverse input column: per session in
    time order, each row's history (:class:`HistoryState`)."""
    inputs = list(HISTORY_INPUTS)
    sessions, times, values = d["session"].to_numpy(), d["t"].to_numpy(float), d[inputs].to_numpy(float)
    names = window.columns()
    out = np.empty((len(d), len(names)))
    for session in pd.unique(sessions):
        at = np.flatnonzero(sessions == session)
        at = at[np.argsort(times[at], kind="stable")]
        state = HistoryState(window, len(inputs))
        for row in at:
            out[row] = state.update(times[row], values[row])
    return d.assign(**dict(zip(names, out.T, strict=True)))


def set_point_ends(d: pd.DataFrame) -> pd.DataFrame:
    """The rows of a path recording a history-aware inverse model learns from: per session, the last row
    under each commanded set-point (``qc_*``) before the next one, in time order. Every frame of a path pairs
    the tip with the command in force, but the commands step from set-point to set-point while the tip moves
    on smoothly, so most frames pair a tip with a command it has not reached yet; at a set-point's end the tip
    is where that command and its history took it. Add the history (:func:`with_history`) before: it is
    computed over every frame."""
    d = d.sort_values(["session", "t"], kind="stable")
    qc = d[[c for c in d if c.startswith("qc_")]].to_numpy(float)
    sessions = d["session"].to_numpy()
    changes = (qc[1:] != qc[:-1]).any(axis=1) | (sessions[1:] != sessions[:-1])
    return d[np.r_[changes, True]]


class HistoryModel(SklearnBaseline):
    """Gradient boosting on the residual of the rigid model (as ``gbr``) from the 7 inputs and their history
    under ``window`` (``with_history(rows, window)``'s columns of its own direction's inputs, which the rows
    must carry)."""

    def __init__(self, direction: str = "forward", window: HistoryWindow = STATIC_POINTS,
                 random_state: int = 0, max_iter: int = 300) -> None:  # fmt: skip
        super().__init__("gbr", direction, random_state=random_state, max_iter=max_iter)
        self.window = window

    @property
    def name(self) -> str:
        return "history"

    def history_inputs(self) -> tuple[str, ...]:
        """The input columns whose history it reads: its own direction's (an inverse input, the rigid IK, is
        NaN out of reach, so a forward model does not read it)."""
        return tuple(c for c in HISTORY_INPUTS if c in self.inputs)

    def _features(self, df: pd.DataFrame) -> np.ndarray:
        names = self.window.columns(self.history_inputs())
        if missing := [c for c in names if c not in df]:
            raise ValueError(
                f"HistoryModel needs the history columns of pipeline.history.with_history (missing "
                f"{missing[0]!r} and {len(missing) - 1} more): add them to the whole dataset before splitting"
            )
        return np.hstack([super()._features(df), df[names].to_numpy(float)])

    def to_dict(self) -> dict:
        window = self.window
        return super().to_dict() | {"lags": window.lags, "time_constants_s": list(window.time_constants_s)}
