"""What stands behind the two emulated Arduino boards: the hardware interfaces the firmware emulators drive
(``PressureHardware``, ``StepperHardware``: the twin in the rig implements them), a board's drifting and
wrapping clock, and simple stand-alone hardware for tests and demos (first-order regulators and transducers,
a stepper with a trapezoidal profile)."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from acquisition.codecs import board_lines as bp

_HALF_WRAP = bp.MICROS_MODULO // 2


class PressureHardware(Protocol):
    """What stands behind the pressure board."""

    def set_pressure(self, channel: int, pa: float) -> None:
        """New regulator set-point (gauge Pa)."""

    def set_valve(self, channel: int, open: bool) -> None:
        """Energise (open) or release a solenoid valve."""

    def advance(self, now_s: float) -> None:
        """Bring the pneumatics up to ``now_s`` (before a setter changes them)."""

    def sample(self, now_s: float) -> tuple[int, int]:
        """ADS1115 counts of channels 0 and 1 at ``now_s``."""
        ...

    def micros(self, now_s: float) -> int:
        """The board's ``micros()`` (own clock, wraps at 2³²)."""
        ...

    def micros_due_s(self, micros: int, now_s: float) -> float:
        """The earliest rig time at which ``micros()`` reads ``micros`` or later (modulo 2³², within half a
        wrap; ``now_s`` if it already does)."""
        ...


class StepperHardware(Protocol):
    """What stands behind the stepper board."""

    def move_to(self, steps: int) -> None:
        """New absolute target (microsteps)."""

    def set_speed(self, steps_s: float, accel: float) -> None:
        """Maximum speed (microsteps/s) and acceleration (microsteps/s²)."""

    def stop(self) -> None:
        """Stop as soon as possible."""

    def position(self, now_s: float) -> int:
        """Position (microsteps) at ``now_s``."""
        ...

    def moving(self, now_s: float) -> bool:
        """Whether the motor is still moving at ``now_s``."""
        ...

    def micros(self, now_s: float) -> int:
        """The board's ``micros()`` (own clock, wraps at 2³²)."""
        ...

    def micros_due_s(self, micros: int, now_s: float) -> float:
        """The earliest rig time at which ``micros()`` reads ``micros`` or later (modulo 2³², within half a
        wrap; ``now_s`` if it already does)."""
        ...


# ---------------------------------------------------------------------------------- simple hardware
class DriftingClock:
    """A board clock: ``micros = (offset + now·(1 + ppm·1e-6))·1e6`` mod 2³²."""

    def __init__(self, drift_ppm: float = 0.0, offset_s: float = 0.0) -> None:
        self.drift_ppm = drift_ppm
        self.offset_s = offset_s

    def micros(self, now_s: float) -> int:
        """The wrapping microsecond counter at host time ``now_s``."""
        return int((self.offset_s + now_s * (1.0 + self.drift_ppm * 1e-6)) * 1e6) % bp.MICROS_MODULO

    def due_s(self, micros: int, now_s: float) -> float:
        """The host time at which the counter reaches ``micros`` (0.1 µs late, so that ``micros()`` surely
        reads it then); ``now_s`` if it already has (within half a wrap)."""
        rate = 1.0 + self.drift_ppm * 1e-6
        raw = int((self.offset_s + now_s * rate) * 1e6)
        ahead = (micros - raw) % bp.MICROS_MODULO
        if ahead == 0 or ahead >= _HALF_WRAP:
            return now_s
        return max(now_s, ((raw + ahead) * 1e-6 - self.offset_s) / rate + 1e-7)


class SimplePressureHardware:
    """Two first-order regulators (τ 30 ms), vent valves (τ 20 ms when open, a GUESS of the plumbing),
    0–4 bar → 0.5–4.5 V transducers, ADS1115 at ±4.096 V (125 µV LSB, 30 µV rms noise, clips at 32767)."""

    tau_s = 0.030
    vent_tau_s = 0.020
    transducer_range_pa = 400_000.0
    noise_v = 30e-6

    def __init__(self, drift_ppm: float = 1500.0, offset_s: float = 0.0, seed: int = 0) -> None:
        self.clock = DriftingClock(drift_ppm, offset_s)
        self.setpoint_pa = [0.0, 0.0]
        self.pressure_pa = [0.0, 0.0]
        self.valve_open = [False, False]
        self._last_s: float | None = None
        self._rng = np.random.default_rng(seed)

    def set_pressure(self, channel: int, pa: float) -> None:
        """New regulator set-point."""
        self.setpoint_pa[channel] = float(pa)

    def set_valve(self, channel: int, open: bool) -> None:
        """An open valve vents its chamber to the atmosphere."""
        self.valve_open[channel] = bool(open)

    def advance(self, now_s: float) -> None:
        """Integrate the chamber pressures up to ``now_s`` (exact for piecewise-constant inputs)."""
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s if self._last_s is None else max(self._last_s, now_s)
        for ch in (0, 1):
            target, tau = (
                (0.0, self.vent_tau_s) if self.valve_open[ch] else (self.setpoint_pa[ch], self.tau_s)
            )
            self.pressure_pa[ch] = target + (self.pressure_pa[ch] - target) * math.exp(-dt / tau)

    def sample(self, now_s: float) -> tuple[int, int]:
        """ADC counts of both transducers."""
        self.advance(now_s)
        counts = []
        for ch in (0, 1):
            volts = 0.5 + 4.0 * self.pressure_pa[ch] / self.transducer_range_pa
            volts += self.noise_v * float(self._rng.standard_normal())
            counts.append(int(np.clip(round(volts / bp.ADC_LSB_V), -32768, 32767)))
        return counts[0], counts[1]

    def micros(self, now_s: float) -> int:
        """The Uno's resonator clock."""
        return self.clock.micros(now_s)

    def micros_due_s(self, micros: int, now_s: float) -> float:
        """When the Uno's clock reads ``micros``."""
        return self.clock.due_s(micros, now_s)


class SimpleStepperHardware:
    """Constant-speed moves (acceleration ignored), instant stop, on a crystal clock (default +40 ppm)."""

    def __init__(self, drift_ppm: float = 40.0, offset_s: float = 0.0) -> None:
        self.clock = DriftingClock(drift_ppm, offset_s)
        self.speed_steps_s = 1000.0
        self.accel_steps_s2 = 5000.0
        self.target = 0
        self._pos = 0.0
        self._last_s: float | None = None

    def _advance(self, now_s: float) -> None:
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s if self._last_s is None else max(self._last_s, now_s)
        remaining = self.target - self._pos
        step = min(abs(remaining), self.speed_steps_s * dt)
        self._pos += math.copysign(step, remaining)

    def move_to(self, steps: int) -> None:
        """New absolute target."""
        self.target = int(steps)

    def set_speed(self, steps_s: float, accel: float) -> None:
        """Speed used from now on; the acceleration is only remembered."""
        self.speed_steps_s, self.accel_steps_s2 = float(steps_s), float(accel)

    def stop(self) -> None:
        """Stop where the motor is."""
        self.target = round(self._pos)
        self._pos = float(self.target)

    def position(self, now_s: float) -> int:
        """Whole microsteps taken so far."""
        self._advance(now_s)
        return math.trunc(self._pos)

    def moving(self, now_s: float) -> bool:
        """True until the target is reached."""
        self._advance(now_s)
        return self.position(now_s) != self.target

    def micros(self, now_s: float) -> int:
        """The Nano's clock."""
        return self.clock.micros(now_s)

    def micros_due_s(self, micros: int, now_s: float) -> float:
        """When the Nano's clock reads ``micros``."""
        return self.clock.due_s(micros, now_s)


# ---------------------------------------------------------------------------------------- emulators
