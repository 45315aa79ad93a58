"""Device clocks and host links: how a device stamps its samples and when the host receives them.

A device counter runs at its own rate: t_dev = (1 + ε)·t + b with ε a few tens of ppm for a crystal and up to
≈ 2000 ppm for the Uno's ceramic resonator; it counts ticks and wraps (Dynamixel Realtime Tick at 32768 ms,
``micros()`` at 2³² µs). The host sees a sample after a one-sided delay: fixed latency plus jitter ≥ 0.
The drawn ε and b are public: they are the truth a fitted clock (``pipeline.clock.ClockFitter``) is
checked against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from acquisition.schemas.stamps import unwrap_ticks  # noqa: F401  (the twin's counters wrap like the devices')

# A sample taken exactly on a tick boundary must count that tick despite float rounding of (1 + ε)·t + b.
_TICK_EPS = 1e-9


@dataclass(frozen=True)
class SimulatedClockSpec:
    """The twin's simulated device counter (made from the description's ``ClockDescription``): tick length
    (s), wrap modulus (None = never wraps), drift spread (ppm, 1σ) and the range [0, offset_max_s) of its
    start offset."""

    tick_s: float
    wrap: int | None
    drift_ppm_sigma: float
    offset_max_s: float

    def __post_init__(self) -> None:
        if not self.tick_s > 0:
            raise ValueError(f"tick_s must be > 0, got {self.tick_s}")
        if self.wrap is not None and self.wrap < 2:
            raise ValueError(f"wrap must be None or ≥ 2, got {self.wrap}")
        if self.drift_ppm_sigma < 0 or self.offset_max_s < 0:
            raise ValueError("drift_ppm_sigma and offset_max_s must be ≥ 0")


class SimulatedClocks:
    """The twin's simulated device clocks, one per robot of a batch, with drawn drift ``drift_ppm`` (B,) and
    offset ``offset_s`` (B,)."""

    def __init__(self, spec: SimulatedClockSpec, batch: int, rng: np.random.Generator) -> None:
        self.spec = spec
        self.drift_ppm: np.ndarray = rng.normal(0.0, spec.drift_ppm_sigma, size=batch)
        self.offset_s: np.ndarray = (
            rng.uniform(0.0, spec.offset_max_s, size=batch) if spec.offset_max_s > 0 else np.zeros(batch)
        )

    @classmethod
    def from_truth(
        cls, spec: SimulatedClockSpec, drift_ppm: np.ndarray, offset_s: np.ndarray
    ) -> SimulatedClocks:
        """Clocks with pinned drift (ppm) and offset (s), both (B,) (tests, or a config that fixes them)."""
        drift = np.atleast_1d(np.asarray(drift_ppm, dtype=float))
        offset = np.atleast_1d(np.asarray(offset_s, dtype=float))
        if drift.ndim != 1 or drift.shape != offset.shape:
            raise ValueError(f"drift_ppm {drift.shape} and offset_s {offset.shape} must both be (B,)")
        clocks = cls.__new__(cls)
        clocks.spec, clocks.drift_ppm, clocks.offset_s = spec, drift, offset
        return clocks

    @property
    def batch(self) -> int:
        """Number of clocks (robots)."""
        return self.drift_ppm.shape[0]

    def device_seconds(self, t: np.ndarray) -> np.ndarray:
        """Device time (1 + ε)·t + b for true times t of shape (B,) or (B, N, ...)."""
        t = np.asarray(t, dtype=float)
        extra = (1,) * max(t.ndim - 1, 0)
        rate = (1.0 + self.drift_ppm * 1e-6).reshape(-1, *extra)
        return rate * t + self.offset_s.reshape(-1, *extra)

    def ticks(self, t: np.ndarray) -> np.ndarray:
        """The device counter (int64) at true times t (B,) or (B, N): floor(device s / tick), wrapped."""
        return self._count(self.device_seconds(t))

    def ticks_at(self, robot: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The counter for flat samples: robot index and true time per sample (same shape)."""
        robot = np.asarray(robot, dtype=np.intp)
        seconds = (1.0 + self.drift_ppm[robot] * 1e-6) * np.asarray(t, dtype=float) + self.offset_s[robot]
        return self._count(seconds)

    def _count(self, seconds: np.ndarray) -> np.ndarray:
        counts = np.floor(seconds / self.spec.tick_s + _TICK_EPS).astype(np.int64)
        return counts % self.spec.wrap if self.spec.wrap is not None else counts


JitterKind = Literal["exponential", "uniform"]


@dataclass(frozen=True)
class HostLinkSpec:
    """USB-serial delivery: fixed latency (s) plus a one-sided random extra delay of scale ``jitter_s``:
    uniform on [0, jitter_s) (FTDI latency timer; mean jitter_s/2) or exponential with mean jitter_s."""

    latency_s: float
    jitter_s: float
    kind: JitterKind = "uniform"

    def __post_init__(self) -> None:
        if self.kind not in ("exponential", "uniform"):
            raise ValueError(f"unknown host link jitter kind {self.kind!r} (exponential or uniform)")
        if self.latency_s < 0 or self.jitter_s < 0:
            raise ValueError("latency_s and jitter_s must be ≥ 0 (the delay is one-sided)")


def host_receive_ns(t: np.ndarray, spec: HostLinkSpec, rng: np.random.Generator) -> np.ndarray:
    """Host receive times (int64 ns) of samples taken at true times t (s): t + latency + jitter ≥ 0."""
    t = np.asarray(t, dtype=float)
    if spec.jitter_s == 0:
        jitter = np.zeros(t.shape)
    elif spec.kind == "exponential":
        jitter = rng.exponential(spec.jitter_s, size=t.shape)
    else:
        jitter = rng.uniform(0.0, spec.jitter_s, size=t.shape)
    return np.round((t + spec.latency_s + jitter) * 1e9).astype(np.int64)
