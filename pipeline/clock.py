"""Device clocks → host time: one-way stamps fitted by their lower envelope.

A device stamps a sample with its counter, t_dev = (1 + ε)·t + b (ticks of ``tick_s``, wrapping); the host
logs it at t + latency + jitter with jitter ≥ 0. So host − device time lies on or above a line, and the line
is the lower envelope: the least-waiting sample of each window (1 s), then a trimmed least-squares line
through those (liblsl / NTP practice; a strict hull would follow a quantised counter's slow phase walk, a
1 ms servo tick polled every 2 ms, and misread it as drift). The fixed latency is
invisible to the fit and is subtracted as a calibration constant. A counter reset (a step that host time does
not show) splits the stamps into segments, each fitted on its own; short ones borrow the long ones' rate.

A counter the host polls (Sync Read, SYNC) is read at instants on the host's clock: when the poll period is a
whole number of ticks every sample sits at the same phase of its tick and that phase walks only ε·T/tick
ticks in T seconds (0.6 tick in 20 s at 30 ppm). The floored counter swallows that walk: host − device time
stays flat between phase slips (the counter stepping one tick more or less than usual), so the drift shows
only as the spacing of slips. With fewer than two slips it is not in the data: the fit says so
(``drift_fitted`` False) and takes the middle of what the stamps allow, |ε| < tick/T with no slip (the
device's nominal rate), 0 < ±ε < tick/max(t*, T − t*) with one slip at t*. Either keeps every sample within
half a tick of its sampling instant: between slips the envelope is flat and is where the samples sit.

Offset convention (the twin's own): ``offset_s`` is the device clock (s, unwrapped counter × tick) at host
time ``ref_ns``, i.e. t_dev = (1 + ε)·(t_host − ref) + offset_s, with t_host the host time of sampling.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from models.estimator import Estimator


@dataclass(frozen=True)
class ClockSegment:
    """Samples [start, stop) between counter resets: a sample taken at device time (s) d has host sampling
    time (s since ref) ``host0_s`` + ``rate``·(d − ``tick0``·tick_s)."""

    start: int
    stop: int
    tick0: int
    host0_s: float
    rate: float  # host seconds per device second, 1 / (1 + ε)

    @property
    def drift_ppm(self) -> float:
        return (1.0 / self.rate - 1.0) * 1e6


@dataclass(frozen=True)
class ClockFit:
    """A fitted device clock: drift ε (ppm), offset (device s at host ``ref_ns``), the residual delay above
    the envelope (jitter, s: median and 95th percentile), sample count and segments (one more than resets)."""

    tick_s: float
    ref_ns: int
    latency_s: float
    segments: tuple[ClockSegment, ...]
    jitter_p50_s: float
    jitter_p95_s: float
    n: int
    stamp_phase: float = 0.5
    drift_fitted: bool = True  # False: too few phase slips to see drift; the nominal rate is used

    @property
    def main(self) -> ClockSegment:
        """The longest segment: the one ``offset_s`` and ``drift_ppm`` describe."""
        return max(self.segments, key=lambda s: s.stop - s.start)

    @property
    def drift_ppm(self) -> float:
        return self.main.drift_ppm

    @property
    def offset_s(self) -> float:
        s = self.main
        return s.tick0 * self.tick_s - s.host0_s / s.rate

    @property
    def resets(self) -> int:
        return len(self.segments) - 1

    def labels(self) -> np.ndarray:
        """The segment index of each fitted sample (n,)."""
        return np.repeat(np.arange(len(self.segments)), [s.stop - s.start for s in self.segments])

    def to_host_ns(self, ticks: np.ndarray, segment: int | np.ndarray = 0) -> np.ndarray:
        """Host time of sampling (int64 ns) of unwrapped device ``ticks`` counted in ``segment`` (index or
        per-sample indices, e.g. ``labels()``)."""
        seg = np.asarray(segment)
        tick0, host0, rate = (np.array([getattr(s, a) for s in self.segments])[seg]
                              for a in ("tick0", "host0_s", "rate"))  # fmt: skip
        elapsed = (np.asarray(ticks, dtype=np.int64) - tick0 + self.stamp_phase) * self.tick_s
        return self.ref_ns + np.round((host0 + rate * elapsed) * 1e9).astype(np.int64)

    def as_dict(self) -> dict:
        """What the report records."""
        segments = [{"start": s.start, "stop": s.stop, "drift_ppm": s.drift_ppm} for s in self.segments]
        return {"offset_s": self.offset_s, "drift_ppm": self.drift_ppm, "jitter_p50_s": self.jitter_p50_s,
                "jitter_p95_s": self.jitter_p95_s, "n": self.n, "resets": self.resets, "ref_ns": self.ref_ns,
                "latency_s": self.latency_s, "drift_fitted": self.drift_fitted,
                "segments": segments}  # fmt: skip


def unwrap_stamps(raw: np.ndarray, host_ns: np.ndarray, tick_s: float, wrap: int | None) -> np.ndarray:
    """Unwrap a wrapping counter (int64 out, from raw[0]) using host time: each step takes the number of
    wraps that brings it closest to the host's step, so gaps longer than half a wrap unwrap right too."""
    raw = np.asarray(raw, dtype=np.int64)
    if wrap is None or raw.size < 2:
        return raw.copy()
    step = np.diff(raw)
    expected = np.diff(np.asarray(host_ns, dtype=np.int64)) * (1e-9 / tick_s)
    turns = np.round((expected - step) / wrap).astype(np.int64)
    return raw[0] + np.concatenate([[0], np.cumsum(step + turns * np.int64(wrap))])


def find_resets(ticks: np.ndarray, host_ns: np.ndarray, tick_s: float, tol_s: float = 0.25) -> np.ndarray:
    """Indices where a new segment starts: the device's step disagrees with the host's by more than
    ``tol_s`` + 1 % of the step (a counter reset, or a jump the host did not see)."""
    dev = np.diff(np.asarray(ticks, dtype=np.int64)) * tick_s
    host = np.diff(np.asarray(host_ns, dtype=np.int64)) * 1e-9
    return np.flatnonzero(np.abs(dev - host) > tol_s + 0.01 * np.abs(host)) + 1


def window_minima(x: np.ndarray, z: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """The lowest point of each ``width``-long window of x: the samples that waited least. A window with under
    half the usual samples (the session's ragged last one) is left out: its minimum waited longer, and on a
    short session that lifted one end of the line by a jitter's worth (−80 ppm on 5–8 s)."""
    group = np.floor((x - x.min()) / width).astype(np.int64)
    if np.all(group[1:] >= group[:-1]) and np.isfinite(z).all():  # in time order (as fits get them): linear
        starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        counts = np.diff(np.r_[starts, group.size])
        lowest = np.repeat(np.minimum.reduceat(z, starts), counts)
        at = np.flatnonzero(z == lowest)  # every sample at its window's minimum; the first of each window:
        mins = at[np.r_[True, group[at][1:] != group[at][:-1]]]
    else:
        order = np.lexsort((z, group))
        starts = np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])
        counts = np.diff(np.r_[starts, order.size])
        mins = order[starts]
    full = counts >= 0.5 * np.median(counts)
    first = mins[full] if full.sum() >= 2 else mins
    return x[first], z[first]


def line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """The least-squares line y = a + c·x through the points, returns (a, c): the centred normal equations
    (what ``np.polyfit(x, y, 1)`` solves, without its Vandermonde matrix and SVD: a fit of a 100k-sample
    stream costs a tenth). x must not be constant."""
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    c = float((dx * (y - ym)).sum() / (dx * dx).sum())  # numpy sums, not BLAS: no threads in a worker
    return ym - c * xm, c


def envelope_line(x: np.ndarray, z: np.ndarray, width: float, slope: float | None = None,
                  trim: float = 5.0) -> tuple[float, float]:  # fmt: skip
    """The line z = a + c·x under the points: the slope by least squares through the window minima of the
    detrended points (refined 3×; windows off the line by more than ``trim`` MADs, a USB stall, dropped),
    the intercept at the lowest kept window minimum. ``slope`` given: only the intercept. Returns (a, c)."""
    c = slope if slope is not None else (line_fit(x, z)[1] if np.ptp(x) > 0 else 0.0)
    xw, zw = window_minima(x, z - c * x, width)
    keep = np.ones(xw.size, bool)
    for _ in range(0 if slope is not None or xw.size < 3 else 3):
        for _ in range(2):
            a0, dc = line_fit(xw[keep], zw[keep])
            r = zw - a0 - dc * xw
            keep = np.abs(r) <= trim * 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-9
            keep |= keep.sum() < 3  # too few left to fit a line: keep every window
        c += float(dc)
        xw, zw = window_minima(x, z - c * x, width)
        keep = np.ones(xw.size, bool) if keep.size != xw.size else keep
    return float(np.min(zw[keep])), c


class ClockFitter(Estimator):
    """A device clock fitted to host time: ``ClockFitter(tick_s).fit(device_ticks, host_ns)``, then
    ``predict(ticks)`` gives the host time of sampling (int64 ns) and ``clock_`` the fit (:class:`ClockFit`).

    ``fit`` takes device ticks (unwrapped, int64, in host order) and host receive times (int64 ns); the
    host times less ``latency_s`` are fitted. ``ref_ns`` (default: the first host time) is where
    ``offset_s`` is read. ``stamp_phase``: where in its tick a sample falls on average (0.5 for a floored
    counter read at any instant, 0 when the count is the sampling event itself, as a tracker frame). Segments
    shorter than ``min_span_s`` of device time keep the rate of the longer ones and fit only their offset.
    ``polled``: the host chooses the sampling instants (see the module docstring); a phase-locked counter
    with fewer than ``min_slips`` phase slips in its long segments gets the nominal rate, unfitted.
    """

    def __init__(self, tick_s: float = 1e-3, latency_s: float = 0.0, ref_ns: int | None = None,
                 stamp_phase: float = 0.5, window_s: float = 1.0, reset_tol_s: float = 0.25,
                 min_span_s: float = 5.0, polled: bool = False, min_slips: int = 2) -> None:  # fmt: skip
        self.tick_s = tick_s
        self.latency_s = latency_s
        self.ref_ns = ref_ns
        self.stamp_phase = stamp_phase
        self.window_s = window_s
        self.reset_tol_s = reset_tol_s
        self.min_span_s = min_span_s
        self.polled = polled
        self.min_slips = min_slips

    def fit(self, device_ticks: np.ndarray, host_ns: np.ndarray) -> ClockFitter:
        ticks = np.asarray(device_ticks, dtype=np.int64)
        host = np.asarray(host_ns, dtype=np.int64)
        if ticks.shape != host.shape or ticks.ndim != 1 or ticks.size < 2:
            raise ValueError(
                f"ClockFitter.fit needs ≥ 2 paired 1-D samples, got {ticks.shape} and {host.shape}"
            )
        tick_s, window_s = self.tick_s, self.window_s
        ref = int(host[0]) if self.ref_ns is None else int(self.ref_ns)
        bounds = np.concatenate([[0], find_resets(ticks, host, tick_s, self.reset_tol_s), [ticks.size]])
        y = (host - ref) * 1e-9 - self.latency_s  # host time of sampling + jitter (s since ref)
        parts = []
        for start, stop in itertools.pairwise(bounds):
            x = (ticks[start:stop] - ticks[start]) * tick_s
            parts.append((start, stop, x, y[start:stop] - x))
        long = [p for p in parts if np.ptp(p[2]) >= self.min_span_s] or [
            max(parts, key=lambda p: np.ptp(p[2]))
        ]
        spans = [(start, stop) for start, stop, _, _ in long]
        resolved = not (self.polled and phase_locked(ticks, spans, self.min_slips))
        fits = {
            a: envelope_line(x, z, _width(x, window_s), None if resolved else -slip_drift(ticks[a:b]))
            for a, b, x, z in long
        }
        shared = float(np.average([fits[p[0]][1] for p in long], weights=[p[1] - p[0] for p in long]))
        segments, residual = [], []
        for start, stop, x, z in parts:
            a, c = fits[start] if start in fits else envelope_line(x, z, _width(x, window_s), shared)
            segments.append(ClockSegment(int(start), int(stop), int(ticks[start]), a, 1.0 + c))
            residual.append(z - a - c * x)
        residual = np.concatenate(residual)
        p50, p95 = np.percentile(residual, [50, 95])
        self.clock_ = ClockFit(
            tick_s, ref, self.latency_s, tuple(segments), float(p50), float(p95), int(ticks.size),
            self.stamp_phase, resolved,
        )  # fmt: skip
        return self

    def predict(self, ticks: np.ndarray, segment: int | np.ndarray = 0) -> np.ndarray:
        """Host time of sampling (int64 ns) of unwrapped device ``ticks`` counted in ``segment``."""
        self.check_fitted()
        return self.clock_.to_host_ns(ticks, segment)


def phase_slips(ticks: np.ndarray) -> tuple[np.ndarray, float]:
    """A polled counter's phase slips, as the signed steps (±1 tick) off the usual (modal) step by index, and
    the share of steps off it (a dithered poll spreads them; a phase-locked one leaves slips and losses)."""
    steps = np.diff(np.asarray(ticks, dtype=np.int64))
    if steps.size == 0:
        return np.zeros(0, np.int64), 0.0
    values, counts = np.unique(steps, return_counts=True)
    off = steps - values[np.argmax(counts)]
    return np.where(np.abs(off) == 1, off, 0), float(np.mean(off != 0))


def slip_drift(ticks: np.ndarray) -> float:
    """The drift ε (fraction) in the middle of what a phase-locked counter with at most one slip allows: 0
    without one, ±1/(2·max(n*, n − n*)) with one at tick n* of n (a tick more than usual: ε > 0)."""
    slips, _ = phase_slips(ticks)
    at = np.flatnonzero(slips)
    if at.size != 1:
        return 0.0
    before, total = float(ticks[at[0]] - ticks[0]), float(ticks[-1] - ticks[0])
    return float(slips[at[0]]) / (2.0 * max(before, total - before, 1.0))


def phase_locked(ticks: np.ndarray, spans: list[tuple[int, int]], min_slips: int = 2,
                 dithered: float = 0.01) -> bool:  # fmt: skip
    """True when the drift of a polled counter is not in its stamps: every sample [start, stop) of ``spans``
    at one phase (under ``dithered`` of the steps off the usual one) and fewer than ``min_slips`` slips."""
    found = [phase_slips(ticks[a:b]) for a, b in spans]
    return max(off for _, off in found) < dithered and sum(np.count_nonzero(s) for s, _ in found) < min_slips


def _width(x: np.ndarray, window_s: float) -> float:
    """Window length: ``window_s``, shorter for a short segment (at least 8 windows)."""
    return max(min(window_s, float(np.ptp(x)) / 8.0), 1e-9)
