"""The tracker's field distortion as the twin fit sees it (issue 33): a smooth bias of the tracked tip that
repeats at each place in the field (metal near the field generator bends its field;
``../shared/reference/unmodelled-effects.md``: 0.5–1 mm RMS, changing over ~50 mm).

Left out of the fit, that bias is 3× the tracker's noise and the fit bends every parameter to explain it
(on a lab arm with 0.7 mm: stiffness ×0.45 to ×1.45, lengths 1 mm off, errors of 5–30 standard errors). Here
it is a Gaussian process over the tracker's frame (a stationary field, each axis's bias correlated over
distance r by s² e^(−r²/2ℓ²), the covariance the twin's field is drawn from) given by ``FEATURES`` random
Fourier features: a linear model with a Gaussian prior on its weights. The fit profiles the weights out of
each residual (their ridge solution, the prior's penalty as rows of their own), so every other parameter is
fitted to what the field cannot explain — and the field's absorption shows in their standard errors. The
fitted weights are the twin's own form of a field (``models.effects.TrackerDistortion`` with ``weights_m``):
the fitted description's twin tracks through the lab's field.

The field's size s, length scale ℓ and the noise σ beside it are not told: they are the likeliest under the
residuals of a fit without the field (maximum likelihood, ℓ on a grid). A field under half the noise is none.
On the lab arm's 0.7 mm field the size comes out 2–2.7× the field's own over the arm's reach (the features
need larger weights to shape a field they were not drawn for); 384 features made it larger still.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from models.effects import TrackerDistortion, random_features, tracker_bias
from models.robot import RobotDescription

FEATURES = 1000  # random Fourier features of the fitted field (the twin's form allows 1024)
PAIRS_POINTS = 2000  # the field's size and length scale are read from at most this many points
LENGTH_SCALES_M = np.geomspace(0.01, 0.3, 10)  # the length scales tried
SMALLEST_FIELD = 0.5  # a field under half the noise (per axis) is none
SEED = 33  # the fitted field's features (a seed of its own: not a drawn twin field's, seed 0)


@dataclass(frozen=True)
class FieldPrior:
    """The field's size ``rms_mm`` (per axis), its ``length_scale_m`` and the residuals' noise ``noise_mm``
    (per axis) beside it."""

    rms_mm: float
    length_scale_m: float
    noise_mm: float


def field_prior(positions_m: np.ndarray, residuals_mm: np.ndarray) -> FieldPrior | None:
    """The field the residuals (n, 3) at ``positions_m`` (n, 3) show: the size s, length scale ℓ and noise σ
    that make them likeliest (each axis's residuals Gaussian with covariance s²ΦΦᵀ + σ²I, Φ the features
    of ℓ; ℓ on a grid, s and σ by maximum likelihood at each); None where s is under ``SMALLEST_FIELD`` of
    σ."""
    n = len(positions_m)
    keep = np.random.default_rng(SEED).permutation(n)[:PAIRS_POINTS] if n > PAIRS_POINTS else np.arange(n)
    x, r = positions_m[keep], residuals_mm[keep]
    r = r - r.mean(axis=0)
    n, total = len(x), float(np.sum(r**2))  # three axes, each n residuals
    best = None
    for length in LENGTH_SCALES_M:
        phi = _features(x, *random_features(SEED, FEATURES, length))
        eigen, vectors = np.linalg.eigh(phi.T @ phi)
        eigen = np.clip(eigen, 0.0, None)
        u2 = np.sum((vectors.T @ (phi.T @ r)) ** 2, axis=1)  # (F,): the residuals' power on each eigenvector

        start = np.log([total / (6 * n), total / (6 * n)])
        fit = minimize(_minus_log_likelihood, start, (u2, eigen, n, total), method="Nelder-Mead",
                       options={"xatol": 1e-4, "fatol": 1e-6})  # fmt: skip
        if best is None or fit.fun < best[0]:
            best = (fit.fun, *np.exp(fit.x), length)
    _, s2, noise2, length = best
    if s2 < (SMALLEST_FIELD**2) * noise2:
        return None
    return FieldPrior(float(np.sqrt(s2)), float(length), float(np.sqrt(noise2)))


def _minus_log_likelihood(z: np.ndarray, u2: np.ndarray, eigen: np.ndarray, n: int, total: float) -> float:
    """−log p of three axes' residuals (n each, squares summing to ``total``) under s²ΦΦᵀ + σ²I, (s², σ²) =
    e^z, from ΦᵀΦ's eigenvalues and the residuals' power ``u2`` on its eigenvectors (Woodbury)."""
    s2, noise2 = np.exp(z)
    quad = (total - np.sum(u2 * s2 / (noise2 + s2 * eigen))) / noise2
    logdet = 3 * ((n - len(eigen)) * np.log(noise2) + np.sum(np.log(noise2 + s2 * eigen)))
    return 0.5 * (quad + logdet)


def _features(positions_m: np.ndarray, omega: np.ndarray, phase: np.ndarray) -> np.ndarray:
    return np.sqrt(2.0 / len(phase)) * np.cos(np.asarray(positions_m, float) @ omega.T + phase)


class FieldBasis:
    """The field at the points ``positions_m`` (n, 3): Φ (n, F) random Fourier features of ``prior``'s
    length scale, weights c (F, 3) with prior N(0, s²), so Φc has the prior's covariance."""

    def __init__(self, positions_m: np.ndarray, prior: FieldPrior, features: int = FEATURES) -> None:
        self.prior = prior
        self.omega, self.phase = random_features(SEED, features, prior.length_scale_m)
        self.phi = self.features(positions_m)
        self.ridge = (prior.noise_mm / prior.rms_mm) ** 2  # σ²/s²: the prior's weight against the noise
        factor = cho_factor(self.phi.T @ self.phi + self.ridge * np.eye(features))
        self._solver = cho_solve(factor, self.phi.T)  # (F, n): the weights' ridge solution, once

    def features(self, positions_m: np.ndarray) -> np.ndarray:
        """Φ at positions (..., 3) (m): (..., F)."""
        return _features(positions_m, self.omega, self.phase)

    def weights(self, residuals_mm: np.ndarray) -> np.ndarray:
        """The field's weights (F, 3) that best explain the residuals (n, 3) under the prior."""
        return self._solver @ residuals_mm

    def project(self, residuals_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the field leaves of the residuals (n, 3) and the prior's penalty on its weights (F × 3,
        √(σ²/s²)·c): the two parts of the residual a fit with the field profiled out minimises."""
        c = self.weights(residuals_mm)
        return residuals_mm - self.phi @ c, np.sqrt(self.ridge) * c


def placement(robot: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
    """The description's tracker placement: (R, t) with p_tracker = R p_base + t (R = Rz·Ry·Rx of its
    roll, pitch and yaw, as the twin places it)."""
    tracker = robot.sensors.tracker
    rotation = Rotation.from_euler("xyz", tracker.base_to_tracker_rpy_rad).as_matrix()
    return rotation, np.asarray(tracker.base_to_tracker_translation_m, float)


def described_bias_m(robot: RobotDescription, positions_m: np.ndarray) -> np.ndarray:
    """The bias (n, 3) (m, base frame) the description's tracker field adds at base-frame positions (zero
    where it has none): what its tracker reports beyond the tip."""
    spec = robot.effects.tracker_distortion
    if spec is None:
        return np.zeros_like(positions_m)
    rotation, shift = placement(robot)
    return tracker_bias(spec, positions_m @ rotation.T + shift) @ rotation


def fitted_distortion(basis: FieldBasis, weights_mm: np.ndarray, rotation: np.ndarray) -> TrackerDistortion:
    """The description's ``tracker_distortion`` of a fitted field: ``weights_mm`` (F, 3) the weights fitted
    to the tip's residuals (prediction − measurement, base frame; the features at tracker-frame positions),
    ``rotation`` the tracker's placement (base → tracker)."""
    scale = np.sqrt(2.0 / len(basis.phase)) * 1e-3  # Φ's normalisation, mm → m
    weights = -scale * weights_mm @ rotation.T  # the reported bias is −residual, in the tracker's frame
    return TrackerDistortion(
        rms_m=float(np.sqrt(3) * basis.prior.rms_mm * 1e-3), length_scale_m=basis.prior.length_scale_m,
        features=len(basis.phase), seed=SEED, weights_m=tuple(map(tuple, weights.round(9).tolist())),
    )  # fmt: skip
