"""Register: the tracker's field-generator frame → the robot base frame, from static points.

The tracker reports the tip coil in its own frame; the robot's base frame differs by an unknown rigid
transform. At static points the model gives the tip in the base frame from the measured joints, so pairs
(tracker position, model tip) fix the transform by least squares (Kabsch–Umeyama), made robust by trimming
pairs beyond ``k_mad`` robust deviations and refitting.

Which pairs, and which model: the rigid FK is wrong by the links' bending under gravity (up to ≈ 30 mm on
the VSL arm at 0.5 bar and 100 g), and that error depends on the pose, so it would bias the fit. The rule:
keep the ``fraction`` (½) of the points whose predicted tip sag |FK(q, δ) − FK(q, 0)| is smallest (δ from
``models.statics.static_deflection`` at the measured pressure and payload: stiff links, light loads, short
lever arms in one number; ``max_payload_kg`` can also exclude loaded points first), and by default
(``deflection=True``) correct their model tip by δ. Measured on twin campaigns of 300 points (6 seeds), error
of the recovered rotation / translation: rigid FK, unloaded points 0.18–0.21° / 0.6–0.7 mm;
deflection-corrected, unloaded points 0.02–0.08° / ≤ 0.32 mm; deflection-corrected, least-sag half of all
points (the default) 0.02–0.04° / ≤ 0.15 mm.

Both registrations are estimators (``models.estimator``) with the same use, ``to_base`` / ``to_tracker``:
:class:`TrackerRegistration` fits the transform on static points; :class:`FixedRegistration` takes one fitted
on another dataset of the same setup (sessions of trajectories only have no static points to fit on).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from models.estimator import Estimator
from models.robot import RobotDescription
from models.statics import static_deflection
from pipeline.datasets import joint_angles
from pipeline.errors import PipelineError
from pipeline.tables import columns

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ResidualStats:
    """Distances between mapped and target points (m)."""

    n: int
    rms: float
    p95: float
    max: float

    @classmethod
    def of(cls, residual: ArrayLike) -> ResidualStats:
        """Stats of residual vectors (n, 3) or distances (n,)."""
        r = np.asarray(residual, float)
        d = np.linalg.norm(r, axis=-1) if r.ndim == 2 else np.abs(r)
        if not len(d):
            return cls(0, float("nan"), float("nan"), float("nan"))
        return cls(len(d), float(np.sqrt(np.mean(d**2))), float(np.percentile(d, 95)), float(d.max()))

    def as_dict(self) -> dict:
        return {"n": self.n, "rms_m": self.rms, "p95_m": self.p95, "max_m": self.max}


@dataclass(frozen=True)
class RigidTransform:
    """x' = s R x + t (s = 1 for a rigid transform)."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    def apply(self, x: ArrayLike) -> np.ndarray:
        """Map points (..., 3)."""
        return self.scale * np.asarray(x, float) @ self.rotation.T + self.translation

    def inverse(self) -> RigidTransform:
        r_inv = self.rotation.T
        return RigidTransform(r_inv, -(r_inv @ self.translation) / self.scale, 1.0 / self.scale)

    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = self.scale * self.rotation, self.translation
        return out

    def residuals(self, src: ArrayLike, dst: ArrayLike) -> ResidualStats:
        return ResidualStats.of(self.apply(src) - np.asarray(dst, float))


def rotation_angle(r: ArrayLike) -> float:
    """Angle (rad) of a rotation matrix: how far ``R_est @ R_true.T`` is from the identity."""
    return float(np.arccos(np.clip((np.trace(np.asarray(r, float)) - 1.0) / 2.0, -1.0, 1.0)))


def kabsch_umeyama(
    src: ArrayLike, dst: ArrayLike, scale: bool = False, weights: ArrayLike | None = None
) -> RigidTransform:
    """The (similarity if ``scale``) transform minimising Σ w |s R src + t − dst|²; R is a proper rotation
    (det +1) even where the best orthogonal fit would be a reflection (Umeyama 1991)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need matching (n ≥ 3, 3) point sets, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    u, sigma, vt = np.linalg.svd((b * w[:, None]).T @ a)  # cross-covariance dst × src
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = (u * d) @ vt
    s = float((sigma * d).sum() / (w @ (a * a).sum(axis=1))) if scale else 1.0
    return RigidTransform(rotation, mu_d - s * rotation @ mu_s, s)


def robust_fit(src: ArrayLike, dst: ArrayLike, k_mad: float = 3.0, iterations: int = 10,
               scale: bool = False, floor_m: float = 1e-5) -> tuple[RigidTransform, np.ndarray]:  # fmt: skip
    """Trimmed least squares: fit, drop pairs whose residual exceeds median + ``k_mad`` · 1.4826 · MAD
    (at least ``floor_m``), refit from the kept pairs, until the kept set stops changing. Returns the
    transform and the inlier mask."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    keep = np.ones(len(src), bool)
    fit = kabsch_umeyama(src, dst, scale)
    for _ in range(iterations):
        d = np.linalg.norm(fit.apply(src) - dst, axis=1)
        med = np.median(d)  # over every pair: robust already, and no peeling of a shrinking set
        limit = max(med + k_mad * 1.4826 * np.median(np.abs(d - med)), floor_m)
        new = d <= limit
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        fit = kabsch_umeyama(src[keep], dst[keep], scale)
    return fit, keep


def model_tip(robot: RobotDescription, q: ArrayLike, pressure_pa: ArrayLike | None = None,
              payload_kg: ArrayLike = 0.0) -> np.ndarray:  # fmt: skip
    """The model's tip (n, 3) in the base frame: the D-H chain at the joints q, with the static deflection
    of the links at the pressures (n, C) and payloads if ``pressure_pa`` is given, rigid otherwise."""
    q = np.asarray(q, float)
    if pressure_pa is None:
        return robot.chain().position(q)
    delta, _ = static_deflection(robot, q, pressure_pa, payload_kg)
    return robot.chain().position(q, delta)


class Registration(Estimator):
    """A fitted tracker → robot base transform (``transform_``): what every registration gives."""

    def to_base(self, x_tracker: ArrayLike) -> np.ndarray:
        """Tracker-frame points (..., 3) in the robot base frame."""
        self.check_fitted()
        return self.transform_.apply(x_tracker)

    def to_tracker(self, x_base: ArrayLike) -> np.ndarray:
        """Robot base-frame points (..., 3) in the tracker frame."""
        self.check_fitted()
        return self.transform_.inverse().apply(x_base)

    def placement(self) -> list[list[float]]:
        """The base → tracker placement as a 4×4 matrix (nested lists: JSON-ready, a dataset card's)."""
        self.check_fitted()
        return self.transform_.inverse().matrix().tolist()


class RegistrationError(PipelineError, ValueError):
    """A registration to borrow that is not there for this robot, or is damaged."""


def borrowed_placement(fitted: dict, robot: str, where: str) -> np.ndarray:
    """The tracker placement (4×4, base → tracker) that dataset ``where`` (``name@version``) fitted for
    ``robot`` among its card's registrations ``fitted`` (``DatasetStore.registrations``); an arm on the same
    mount (the rigid-link arm in place of the VSL arm) shares it, so a card of one robot serves any.
    ``RegistrationError`` that says which dataset has none for this robot, or is damaged."""
    mine = fitted.get(robot) or (next(iter(fitted.values())) if len(fitted) == 1 else None)
    if not isinstance(mine, dict):
        raise RegistrationError(f"dataset {where} has no registration for robot {robot!r} (its card has "
                                f"{', '.join(fitted) or 'none'}): borrow one from a dataset of {robot}'s "
                                "sessions")  # fmt: skip
    try:
        placement = np.asarray(mine["base_to_tracker"], float)
        if placement.shape != (4, 4) or not np.isfinite(placement).all():
            raise ValueError(f"base_to_tracker is not a finite 4×4 matrix (shape {placement.shape})")
    except (KeyError, TypeError, ValueError) as exc:
        why = f"{type(exc).__name__}: {exc}"
        raise RegistrationError(f"dataset {where}: its registration for {robot!r} is damaged ({why}); "
                                "build that dataset again") from exc  # fmt: skip
    return placement


class FixedRegistration(Registration):
    """A registration fitted elsewhere (another dataset of the same setup), applied as it is:
    ``FixedRegistration(base_to_tracker, from_dataset).fit()`` takes the placement a dataset card recorded
    (4×4, base → tracker) and learns ``transform_`` (tracker → base). ``fit`` takes the points of the
    estimator contract and ignores them: nothing is learned from this dataset's points."""

    def __init__(self, base_to_tracker: ArrayLike | None = None, from_dataset: str = "") -> None:
        self.base_to_tracker = base_to_tracker
        self.from_dataset = from_dataset

    def fit(self, points: pd.DataFrame | None = None) -> FixedRegistration:
        placement = np.asarray(self.base_to_tracker, float)
        if placement.shape != (4, 4) or not np.isfinite(placement).all():
            raise ValueError(f"base_to_tracker must be a finite 4×4 matrix, got shape {placement.shape}")
        self.transform_ = RigidTransform(placement[:3, :3], placement[:3, 3]).inverse()
        return self

    def summary(self) -> dict:
        """JSON-ready: the placement and the dataset it came from."""
        return {"base_to_tracker": self.placement(), "from_dataset": self.from_dataset}


class TrackerRegistration(Registration):
    """The tracker → robot base transform fitted on static points by the rule in the module docstring:
    ``TrackerRegistration(robot).fit(points)``, then ``to_base(x_tracker)``.

    ``fit`` takes static points (timeline columns ``tracker_position_0..2``, ``servo_position_*``,
    ``stepper_position_*``, ``pressure_*`` and ``payload_kg``); at least ``min_pairs`` pairs are kept (all
    points are ranked if too few pass ``max_payload_kg``). It learns ``transform_`` (tracker → base),
    ``residuals_`` (of the inlier pairs of the final fit), ``residuals_selected_`` (of every selected pair),
    ``n_points_``, ``n_selected_``, ``n_trimmed_`` and ``used_`` (row positions of the inlier pairs).
    """

    def __init__(self, robot: RobotDescription | None = None, deflection: bool = True,
                 max_payload_kg: float | None = None, fraction: float = 0.5, min_pairs: int = 12,
                 k_mad: float = 3.0, iterations: int = 10) -> None:  # fmt: skip
        self.robot = robot
        self.deflection = deflection
        self.max_payload_kg = max_payload_kg
        self.fraction = fraction
        self.min_pairs = min_pairs
        self.k_mad = k_mad
        self.iterations = iterations

    def fit(self, points: pd.DataFrame) -> TrackerRegistration:
        robot = self.robot
        if robot is None:
            raise ValueError("TrackerRegistration needs the robot whose base the tracker is registered to")
        x = columns(points, "tracker_position")
        q = joint_angles(points, robot)
        pressure = columns(points, "pressure")
        payload = points["payload_kg"].to_numpy(float) if "payload_kg" in points else np.zeros(len(points))
        valid = (
            np.isfinite(x).all(1)
            & np.isfinite(q).all(1)
            & np.isfinite(pressure).all(1)
            & np.isfinite(payload)
        )
        sag = np.full(len(points), np.inf)
        sag[valid] = np.linalg.norm(
            model_tip(robot, q[valid], pressure[valid], payload[valid]) - model_tip(robot, q[valid]), axis=1
        )
        limit = np.inf if self.max_payload_kg is None else self.max_payload_kg
        candidates = valid & (payload <= limit)
        if candidates.sum() < self.min_pairs:
            log.warning("only %d points with payload ≤ %s kg: ranking all by predicted sag", candidates.sum(),
                        self.max_payload_kg)  # fmt: skip
            candidates = valid
        n_keep = max(min(self.min_pairs, int(candidates.sum())), round(self.fraction * int(candidates.sum())))
        order = np.flatnonzero(candidates)[np.argsort(sag[candidates], kind="stable")]
        selected = np.sort(order[:n_keep])
        if len(selected) < 3:
            raise ValueError(f"registration needs at least 3 valid static points, got {len(selected)}")
        src = x[selected]
        dst = model_tip(
            robot, q[selected], pressure[selected] if self.deflection else None, payload[selected]
        )
        fit, inlier = robust_fit(src, dst, self.k_mad, self.iterations)
        self.transform_ = fit
        self.residuals_ = fit.residuals(src[inlier], dst[inlier])
        self.residuals_selected_ = fit.residuals(src, dst)
        self.n_points_, self.n_selected_ = len(points), len(selected)
        self.n_trimmed_ = int((~inlier).sum())
        self.used_ = selected[inlier]
        log.debug("registered: %d of %d pairs, rms %.3f mm", len(self.used_), len(points),
                  self.residuals_.rms * 1e3)  # fmt: skip
        return self

    def summary(self) -> dict:
        """JSON-ready: the base → tracker placement (4×4) and the fit's counts and residuals."""
        return {
            "base_to_tracker": self.placement(),
            "residuals": self.residuals_.as_dict(),
            "residuals_selected": self.residuals_selected_.as_dict(),
            "points": self.n_points_, "selected": self.n_selected_, "trimmed": self.n_trimmed_,
            "deflection": self.deflection,
        }  # fmt: skip
