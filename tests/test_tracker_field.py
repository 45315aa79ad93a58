"""The tracker's field distortion as the twin fit sees it (``pipeline.tracker_field``): its size read from
residuals, none where they are noise, and the field profiled out of them."""

from __future__ import annotations

import numpy as np

from models.effects import TrackerDistortion, tracker_bias
from pipeline.tracker_field import FEATURES, FieldBasis, FieldPrior, field_prior

FIELD = TrackerDistortion(rms_m=0.0007, length_scale_m=0.05, seed=0)  # vsl_unmodelled's
NOISE_MM = 0.12  # the settled points' noise per axis (the lab arm's fit: 0.120 mm)


def _points(seed: int = 1, n: int = 2000) -> np.ndarray:
    """Positions (m) over an arm's reach."""
    return np.random.default_rng(seed).uniform([-0.1, -0.3, 0.0], [0.4, 0.3, 0.4], (n, 3))


def test_a_distorted_field_is_read_from_the_residuals_with_its_size():
    x = _points()
    bias = tracker_bias(FIELD, x) * 1e3
    residuals = bias + np.random.default_rng(2).normal(0.0, NOISE_MM, x.shape)
    prior = field_prior(x, residuals)
    assert prior is not None
    realised = float(np.sqrt(np.mean(bias**2)))  # this draw's size per axis over these points
    assert realised / 2 < prior.rms_mm < 2 * realised
    assert 0.025 < prior.length_scale_m < 0.1
    assert abs(prior.noise_mm / NOISE_MM - 1) < 0.25


def test_residuals_that_are_noise_show_no_field():
    x = _points()
    assert field_prior(x, np.random.default_rng(3).normal(0.0, NOISE_MM, x.shape)) is None


def test_the_field_is_profiled_out_and_its_weights_penalised():
    x = _points()
    bias = tracker_bias(FIELD, x) * 1e3
    residuals = bias + np.random.default_rng(4).normal(0.0, NOISE_MM, x.shape)
    basis = FieldBasis(x, FieldPrior(rms_mm=0.4, length_scale_m=0.05, noise_mm=NOISE_MM))
    left, penalty = basis.project(residuals)
    assert left.shape == x.shape and penalty.shape == (FEATURES, 3)
    # what the field leaves is mostly the noise: far under the field's own size
    assert np.sqrt(np.mean(left**2)) < 0.5 * np.sqrt(np.mean(bias**2))
    # a field the basis explains exactly costs its weights' prior, nothing else
    weights = np.random.default_rng(5).normal(0.0, 0.4, (FEATURES, 3))
    left, penalty = basis.project(basis.phi @ weights)
    assert np.sum(left**2) + np.sum(penalty**2) <= np.sum((np.sqrt(basis.ridge) * weights) ** 2) + 1e-9


def test_the_report_says_the_field_a_fit_found(tmp_path):
    """The report's twin section says a fitted field's size beside the tip's residual."""
    import json

    from analysis.lab_figures import Results
    from analysis.twin_report import twin_against_robot
    from pipeline.lab import Lab

    lab = Lab(tmp_path / "lab")
    record = {"name": "vsl_fitted", "file": "vsl_fitted.yaml", "dataset": "campaign@v1", "code_version": "t",
              "points": 3000, "sessions": 16, "residual_rms_mm": 0.12, "registration_correction": {},
              "tracker_field": {"rms_mm": 0.84, "length_scale_mm": 66.2, "noise_mm": 0.14},
              "parameters": {"upper_vsl.k@1bar": {"value": 64.7, "stderr": 0.8, "nominal": 80.0}},
              "not_identifiable": {"l2_m": "the tracker's field is distorted"}}  # fmt: skip
    path = lab.twin.fit("vsl_fitted")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    res = Results()
    twin_against_robot(lab, res, tmp_path / "figures")
    words = res.texts["your twin: vsl_fitted, fitted beside nominal"]
    assert "field is distorted: 0.84 mm per axis over 66 mm" in words and res.missing == {}
