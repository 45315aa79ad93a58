"""Device clocks → host time: one-way stamps fitted by their lower envelope.

A device stamps a sample with its counter, t_dev = (1 + ε)·t + b (ticks of ``tick_s``, wrapping); the host
logs it at t + latency + jitter with jitter ≥ 0. So host − device time lies on or above a line, and the line
is the lower envelope: the least-waiting sample of each window (1 s), then a trimmed least-squares line
through those (liblsl / NTP practice; a strict hull would follow a quantised counter's slow phase walk, a
1 ms servo tick polled every 2 ms, and misread it as drift). The fixed latency is
invisible to the fit and is subtracted as a calibration constant. A counter reset (a step that host time does
not show) splits the stamps into segments, each fitted on its own; short ones borrow the long ones' rate.

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
                "latency_s": self.latency_s, "segments": segments}  # fmt: skip


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
    """The lowest point of each ``width``-long window of x: the samples that waited least."""
    group = np.floor((x - x.min()) / width).astype(np.int64)
    order = np.lexsort((z, group))
    first = order[np.flatnonzero(np.r_[True, group[order][1:] != group[order][:-1]])]
    return x[first], z[first]


def envelope_line(x: np.ndarray, z: np.ndarray, width: float, slope: float | None = None,
                  trim: float = 5.0) -> tuple[float, float]:  # fmt: skip
    """The line z = a + c·x under the points: the slope by least squares through the window minima of the
    detrended points (refined 3×; windows off the line by more than ``trim`` MADs, a USB stall, dropped),
    the intercept at the lowest kept window minimum. ``slope`` given: only the intercept. Returns (a, c)."""
    c = slope if slope is not None else (float(np.polyfit(x, z, 1)[0]) if np.ptp(x) > 0 else 0.0)
    xw, zw = window_minima(x, z - c * x, width)
    keep = np.ones(xw.size, bool)
    for _ in range(0 if slope is not None or xw.size < 3 else 3):
        for _ in range(2):
            dc, a0 = np.polyfit(xw[keep], zw[keep], 1)
            r = zw - a0 - dc * xw
            keep = np.abs(r) <= trim * 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-9
            keep |= keep.sum() < 3  # too few left to fit a line: keep every window
        c += float(dc)
        xw, zw = window_minima(x, z - c * x, width)
        keep = np.ones(xw.size, bool) if keep.size != xw.size else keep
    return float(np.min(zw[keep])), c


class ClockModel(Estimator):
    """A device clock fitted to host time: ``ClockModel(tick_s).fit(device_ticks, host_ns)``, then
    ``predict(ticks)`` gives the host time of sampling (int64 ns) and ``clock_`` the fit (:class:`ClockFit`).

    ``fit`` takes device ticks (unwrapped, int64, in host order) and host receive times (int64 ns); the
    host times less ``latency_s`` are fitted. ``ref_ns`` (default: the first host time) is where
    ``offset_s`` is read. ``stamp_phase``: where in its tick a sample falls on average (0.5 for a floored
    counter read at any instant, 0 when the count is the sampling event itself, as a tracker frame). Segments
    shorter than ``min_span_s`` of device time keep the rate of the longer ones and fit only their offset.
    """

    def __init__(self, tick_s: float = 1e-3, latency_s: float = 0.0, ref_ns: int | None = None,
                 stamp_phase: float = 0.5, window_s: float = 1.0, reset_tol_s: float = 0.25,
                 min_span_s: float = 5.0) -> None:  # fmt: skip
        self.tick_s = tick_s
        self.latency_s = latency_s
        self.ref_ns = ref_ns
        self.stamp_phase = stamp_phase
        self.window_s = window_s
        self.reset_tol_s = reset_tol_s
        self.min_span_s = min_span_s

    def fit(self, device_ticks: np.ndarray, host_ns: np.ndarray) -> ClockModel:
        ticks = np.asarray(device_ticks, dtype=np.int64)
        host = np.asarray(host_ns, dtype=np.int64)
        if ticks.shape != host.shape or ticks.ndim != 1 or ticks.size < 2:
            raise ValueError(
                f"ClockModel.fit needs ≥ 2 paired 1-D samples, got {ticks.shape} and {host.shape}"
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
        fits = {p[0]: envelope_line(p[2], p[3], _width(p[2], window_s)) for p in long}
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
            self.stamp_phase,
        )  # fmt: skip
        return self

    def predict(self, ticks: np.ndarray, segment: int | np.ndarray = 0) -> np.ndarray:
        """Host time of sampling (int64 ns) of unwrapped device ``ticks`` counted in ``segment``."""
        self.check_fitted()
        return self.clock_.to_host_ns(ticks, segment)


def _width(x: np.ndarray, window_s: float) -> float:
    """Window length: ``window_s``, shorter for a short segment (at least 8 windows)."""
    return max(min(window_s, float(np.ptp(x)) / 8.0), 1e-9)
