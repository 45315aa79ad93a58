"""What the real lab does that vslab's models leave out (issue 19), for the twin to add on request.

Each effect is named after its physical cause and sized from a published measurement (SOURCE) or, where
none was found, marked ASSUMED; ``../shared/reference/unmodelled-effects.md`` lists the sources. Every effect
is off unless a robot description switches it on in its ``effects:`` section, so the nominal twin stays the
PRBM the grey box shares its equations with, and a harder twin is a description away
(``configs/robots/vsl_unmodelled.yaml`` extends ``vsl`` with them).

- ``tracker_distortion``: metal near an EM tracker's field generator bends its field, so the reported position
  carries a smooth bias that repeats at each place in the field. The twin draws one field per description (a
  stationary random field of a given RMS and length scale). A static map of the pose can learn it; the PRBM
  cannot.
- ``creep``: a pressurised polymer link keeps bending for seconds to minutes after its load changes (Prony
  series: the bending tends to δ_el (1 + Σ aᵢ) with time constants τᵢ). Equal joint angles, pressures and
  currents then give different tips, by the load history: no static map can predict that. Its terms are
  Maxwell branches beside the links' rate-independent Bouc–Wen loop, so the hysteresis under a cycled load
  depends on the rate too (largest near a period of 2πτᵢ).
- ``elongation``: a pressurised tube's wall stretches along its axis too (a thin closed tube: ε_z =
  (p r / E t)(½ − ν), zero only for an incompressible wall), so each pressurised link is L₀ (1 + ε p) long.
  At fixed joints the tip moves with the pressure, apart from the bending; a model with p among its inputs
  can learn it, the PRBM's fixed lengths cannot.
- ``hoses``: the pneumatic tubes and cables crossing a joint pull it toward where they hang slack, a torque
  that depends on the pose. The drive holds it, so the joint's current no longer measures gravity and payload
  alone (the grey box infers the payload from it) and its droop grows. A static map of (q, i) can learn it.

The functions here are the pure parts the twin's sensors (``tracker_bias``) and kernel (``creep_rest``) use.
"""

from __future__ import annotations

import functools

import numpy as np
from pydantic import Field, model_validator

from models.description_part import Part, PositiveFloat


class TrackerDistortion(Part):
    """A smooth bias of the tracker's reported position, a function of where the coil is in the field
    generator's frame: a stationary random field (``features`` random Fourier features, drawn once from
    ``seed``) whose bias vector has RMS ``rms_m`` and changes over ``length_scale_m``. ``weights_m``: the
    features' weights (one bias vector each, m) where a lab's field was fitted (``vslab twin fit``) instead
    of drawn; the features' frequencies and phases are still drawn from ``seed``."""

    rms_m: PositiveFloat
    length_scale_m: PositiveFloat
    features: int = Field(default=64, ge=8, le=1024)
    seed: int = 0
    weights_m: tuple[tuple[float, float, float], ...] | None = None

    @model_validator(mode="after")
    def _one_weight_a_feature(self) -> TrackerDistortion:
        if self.weights_m is not None and len(self.weights_m) != self.features:
            raise ValueError(f"weights_m has {len(self.weights_m)} rows for {self.features} features")
        return self


class Creep(Part):
    """Creep of the pressurised links: element i's state xᵢ follows τᵢ ẋᵢ = aᵢ δ_el − xᵢ, with δ_el = τ/k the
    link's elastic bending under its static load, and the link bends by δ_el + Σ xᵢ."""

    fractions: tuple[PositiveFloat, ...] = Field(min_length=1)
    time_constants_s: tuple[PositiveFloat, ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> Creep:
        if len(self.fractions) != len(self.time_constants_s):
            raise ValueError(
                f"fractions has {len(self.fractions)} entries but time_constants_s has "
                f"{len(self.time_constants_s)}"
            )
        if (total := sum(self.fractions)) >= 1.0:
            raise ValueError(f"fractions sum to {total:g}: creep must stay below the elastic bending")
        return self


class Elongation(Part):
    """Pressurised links lengthen: a link with a pressure channel is L₀ (1 + ε p) long at its gauge pressure
    p, ε = ``strain_per_bar`` per bar (its virtual joints' rows and the row of the joint it follows)."""

    strain_per_bar: PositiveFloat

    @property
    def strain_per_pa(self) -> float:
        return self.strain_per_bar / 1e5


class JointHoses(Part):
    """The tubes and cables crossing one actuated joint: a torque −K (q − q_slack) on it."""

    stiffness_nm_per_rad: PositiveFloat
    slack_rad: float


class Hoses(Part):
    """Tubes and cables crossing the actuated joints pull each toward the angle where they hang slack. The
    joint's drive holds that torque too: its current shows it and its droop grows with it. Keyed by joint."""

    joints: dict[str, JointHoses] = Field(min_length=1)


class EffectsSpec(Part):
    """The unmodelled effects a description switches on (a missing entry is off)."""

    tracker_distortion: TrackerDistortion | None = None
    creep: Creep | None = None
    hoses: Hoses | None = None
    elongation: Elongation | None = None

    @property
    def active(self) -> list[str]:
        """The names of the effects switched on."""
        return [name for name in type(self).model_fields if getattr(self, name) is not None]


# ------------------------------------------------------------------------------------ tracker distortion
def random_features(seed: int, features: int, length_scale_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The frequencies (N, 3) (rad/m) and phases (N,) of a field's random Fourier features, drawn from
    ``seed``: cos(x·ωᵢ + φᵢ) sum to a squared-exponential correlation over ``length_scale_m``."""
    rng = np.random.default_rng(seed)
    omega = rng.normal(0.0, 1.0 / length_scale_m, (features, 3))
    return omega, rng.uniform(0.0, 2 * np.pi, features)


@functools.lru_cache(maxsize=16)
def _field(spec: TrackerDistortion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frequencies (N, 3) (rad/m), phases (N,) and weights (N, 3) (m) of the distortion's random field."""
    rng = np.random.default_rng(spec.seed)
    n = spec.features
    omega = rng.normal(0.0, 1.0 / spec.length_scale_m, (n, 3))  # a squared-exponential correlation
    phase = rng.uniform(0.0, 2 * np.pi, n)  # (the draws of ``random_features``, in its order)
    weight = rng.normal(0.0, 1.0, (n, 3)) * spec.rms_m * np.sqrt(2.0 / (3 * n))  # E|b|² = rms²
    if spec.weights_m is not None:  # a lab's field, fitted
        weight = np.array(spec.weights_m, float)
    for a in (omega, phase, weight):
        a.flags.writeable = False
    return omega, phase, weight


def tracker_bias(spec: TrackerDistortion, position_m: np.ndarray) -> np.ndarray:
    """The distortion's bias (..., 3) (m) at tracker-frame positions (..., 3) (m): the same position always
    gets the same bias; two positions r apart are correlated by e^(−r²/2ℓ²) (0.61 at one length scale ℓ,
    0.14 at two, nearly independent beyond)."""
    omega, phase, weight = _field(spec)
    return np.cos(np.asarray(position_m, float) @ omega.T + phase) @ weight


# ------------------------------------------------------------------------------------------------- creep
def creep_rest(spec: Creep | None, elastic_rad: np.ndarray) -> np.ndarray:
    """The creep elements' states (..., E) of links that have held their elastic bending ``elastic_rad``
    (...) long enough: xᵢ = aᵢ δ_el. E = 0 without creep."""
    fractions = np.asarray(spec.fractions if spec is not None else (), float)
    return np.asarray(elastic_rad, float)[..., None] * fractions
