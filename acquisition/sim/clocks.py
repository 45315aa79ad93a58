"""Device clocks and host links: how a device stamps its samples and when the host receives them.

A device counter runs at its own rate: t_dev = (1 + ε)·t + b with ε a few tens of ppm for a crystal and up to
≈ 2000 ppm for the Uno's ceramic resonator; it counts ticks and wraps (Dynamixel Realtime Tick at 32768 ms,
``micros()`` at 2³² µs). The host sees a sample after a one-sided delay: fixed latency plus jitter ≥ 0.
The drawn ε and b are public: they are the truth a fitted clock model is checked against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class ClockSpec:
    """A device counter: tick length, wrap modulus (None = never wraps), drift spread, start offset range."""

    tick_s: float
    wrap: int | None
    drift_ppm_sigma: float
    offset_max_s: float


class DeviceClocks:
    """One clock per robot of a batch, with drawn drift ``drift_ppm`` (B,) and offset ``offset_s`` (B,)."""

    def __init__(self, spec: ClockSpec, batch: int, rng: np.random.Generator) -> None:
        self.spec = spec
        self.drift_ppm = rng.normal(0.0, spec.drift_ppm_sigma, size=batch)
        self.offset_s = (
            rng.uniform(0.0, spec.offset_max_s, size=batch) if spec.offset_max_s > 0 else np.zeros(batch)
        )

    @classmethod
    def from_truth(cls, spec: ClockSpec, drift_ppm: np.ndarray, offset_s: np.ndarray) -> DeviceClocks:
        """Clocks with pinned drift and offset (tests, or a config that fixes them)."""
        clocks = cls.__new__(cls)
        clocks.spec = spec
        clocks.drift_ppm = np.asarray(drift_ppm, dtype=float)
        clocks.offset_s = np.asarray(offset_s, dtype=float)
        return clocks

    def device_seconds(self, t: np.ndarray) -> np.ndarray:
        """Device time (1 + ε)·t + b for true times t of shape (B,) or (B, N)."""
        t = np.asarray(t, dtype=float)
        extra = (1,) * (t.ndim - 1)
        rate = (1.0 + self.drift_ppm * 1e-6).reshape(-1, *extra)
        return rate * t + self.offset_s.reshape(-1, *extra)

    def ticks(self, t: np.ndarray) -> np.ndarray:
        """The device counter at true times t (B,) or (B, N): whole ticks, wrapped."""
        return self._count(self.device_seconds(t))

    def ticks_at(self, robot: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The counter for flat samples: robot index and true time per sample."""
        seconds = (1.0 + self.drift_ppm[robot] * 1e-6) * t + self.offset_s[robot]
        return self._count(seconds)

    def _count(self, seconds: np.ndarray) -> np.ndarray:
        counts = np.floor(seconds / self.spec.tick_s + 1e-9).astype(np.int64)
        return counts % self.spec.wrap if self.spec.wrap is not None else counts


def unwrap_ticks(ticks: np.ndarray, wrap: int) -> np.ndarray:
    """Undo counter wraps in a 1-D sequence (assumes consecutive samples are less than half a wrap apart)."""
    ticks = np.asarray(ticks, dtype=np.int64)
    step = np.diff(ticks)
    wraps = np.concatenate([[0], np.cumsum(step < -(wrap // 2)) - np.cumsum(step > wrap // 2)])
    return ticks + wraps * wrap


@dataclass(frozen=True)
class HostLinkSpec:
    """USB-serial delivery: fixed latency plus a one-sided random extra delay (never negative)."""

    latency_s: float
    jitter_s: float
    kind: Literal["exponential", "uniform"] = "uniform"


def host_receive_ns(t: np.ndarray, spec: HostLinkSpec, rng: np.random.Generator) -> np.ndarray:
    """Host receive times (int64 ns) of samples taken at true times t."""
    t = np.asarray(t, dtype=float)
    if spec.kind == "exponential":
        jitter = rng.exponential(spec.jitter_s, size=t.shape) if spec.jitter_s > 0 else np.zeros(t.shape)
    elif spec.kind == "uniform":
        jitter = rng.uniform(0.0, spec.jitter_s, size=t.shape)
    else:
        raise ValueError(f"unknown host link jitter kind {spec.kind!r} (exponential or uniform)")
    return np.round((t + spec.latency_s + jitter) * 1e9).astype(np.int64)
