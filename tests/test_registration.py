"""pipeline.registration: Kabsch–Umeyama, trimmed refits, and the tracker → base registration on the twin."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from twin_timeline import sessions, timeline, true_base_to_tracker

from acquisition.recorder.sessions import SessionStore
from pipeline.registration import (
    ResidualStats,
    RigidTransform,
    TrackerRegistration,
    kabsch_umeyama,
    robust_fit,
    rotation_angle,
)
from pipeline.segment import static_points
from twin.runner import simulate_experiment
from twin.sensors import rotation_from_rpy


def _random_transform(rng: np.random.Generator, scale: float = 1.0) -> RigidTransform:
    return RigidTransform(rotation_from_rpy(*rng.uniform(-np.pi, np.pi, 3)), rng.normal(0, 0.3, 3), scale)


def test_kabsch_umeyama_recovers_rigid_and_similarity_transforms():
    rng = np.random.default_rng(0)
    src = rng.normal(0, 0.1, (50, 3))
    for scale in (False, True):
        truth = _random_transform(rng, 1.7 if scale else 1.0)
        fit = kabsch_umeyama(src, truth.apply(src), scale=scale)
        assert np.allclose(fit.matrix(), truth.matrix(), atol=1e-12)
        assert fit.residuals(src, truth.apply(src)).max < 1e-12
        back = fit.inverse().apply(fit.apply(src))
        assert np.allclose(back, src, atol=1e-12)


def test_kabsch_umeyama_returns_a_rotation_for_mirrored_data():
    rng = np.random.default_rng(1)
    src = rng.normal(0, 0.1, (30, 3))
    fit = kabsch_umeyama(src, src * np.array([1.0, 1.0, -1.0]))  # the best orthogonal map is a reflection
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
    assert np.allclose(fit.rotation @ fit.rotation.T, np.eye(3), atol=1e-12)


def test_residual_stats():
    stats = ResidualStats.of(np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]]))
    assert (stats.n, stats.rms, stats.max) == (2, pytest.approx(np.sqrt(12.5)), 5.0)
    assert stats.p95 == pytest.approx(4.75)


def test_robust_fit_trims_outliers():
    rng = np.random.default_rng(2)
    src = rng.uniform(-0.2, 0.2, (200, 3))
    truth = _random_transform(rng)
    dst = truth.apply(src) + rng.normal(0, 2.5e-4, src.shape)
    bad = rng.choice(200, 15, replace=False)
    dst[bad] += rng.normal(0, 0.02, (15, 3))
    fit, inlier = robust_fit(src, dst)
    assert not inlier[bad].any() and inlier.sum() > 170
    assert np.degrees(rotation_angle(fit.rotation @ truth.rotation.T)) < 0.02
    assert np.linalg.norm(fit.translation - truth.translation) < 1e-4
    plain = kabsch_umeyama(src, dst)
    assert np.linalg.norm(plain.translation - truth.translation) > 5 * np.linalg.norm(
        fit.translation - truth.translation
    )


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """Static points of a 300-point twin campaign (30 benches) and the twin's true base → tracker (R, t)."""
    root = tmp_path_factory.mktemp("register")
    simulate_experiment("campaign", SessionStore(root), overrides={"points": 300}, benches=30, seed=0)
    tables = sessions(root)
    points = pd.concat([static_points(timeline(s), s.events, s.t0_ns) for s in tables], ignore_index=True)
    return points, tables[0].robot, true_base_to_tracker(tables[0])


def _errors(registration, truth) -> tuple[float, float]:
    """Rotation angle (deg) of R_est R_trueᵀ and translation error (mm) of the base → tracker transform."""
    est = registration.transform_.inverse()
    r_true, t_true = truth
    return np.degrees(rotation_angle(est.rotation @ r_true.T)), np.linalg.norm(est.translation - t_true) * 1e3


@pytest.mark.slow
@pytest.mark.slow
def test_registration_recovers_the_tracker_placement(campaign):
    points, robot, truth = campaign
    assert len(points) == 300
    reg = TrackerRegistration(robot).fit(points)
    angle, shift = _errors(reg, truth)
    assert angle < 0.1 and shift < 0.5
    assert reg.n_selected_ == 150 and reg.residuals_.rms < 5e-4  # what is left: hysteresis, encoder steps
    rigid_angle, _ = _errors(TrackerRegistration(robot, deflection=False).fit(points), truth)
    assert rigid_angle > 2 * angle  # the rigid FK's sag biases the fit
    summary = reg.summary()
    assert np.allclose(summary["base_to_tracker"], reg.transform_.inverse().matrix())
    x = points[[f"tracker_position_{k}" for k in range(3)]].to_numpy()
    assert np.allclose(reg.to_tracker(reg.to_base(x)), x)


def test_registration_survives_bad_points(campaign):
    points, robot, truth = campaign
    rng = np.random.default_rng(5)
    corrupt = points.copy()
    bad = rng.choice(len(points), 15, replace=False)
    for k in range(3):
        corrupt.loc[bad, f"tracker_position_{k}"] += rng.normal(0, 0.01, len(bad))
    reg = TrackerRegistration(robot).fit(corrupt)
    angle, shift = _errors(reg, truth)
    assert angle < 0.1 and shift < 0.5
    assert not np.isin(bad, reg.used_).any() and reg.n_trimmed_ >= 5
