"""One contract for every fitted thing (models/estimator.py, scikit-learn's): the clock model, the tracker
registration, every baseline and the hybrid networks, run through the same checks.

- the constructor only stores its parameters: ``get_params`` gives back what was passed, nothing learned;
- ``fit`` returns ``self`` and learns attributes ending in ``_``, none of which exist before;
- use before ``fit`` raises the one ``NotFittedError``;
- the same parameters and seed give the same result; ``clone`` / ``set_params`` make a fresh, equal one;
- what the registry saves (a network, a baseline's card) comes back the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone

from models.errors import NotFittedError
from models.estimator import Estimator
from models.hybrid import preset
from models.robot import load_robot
from pipeline import baselines as B
from pipeline.clock import ClockModel
from pipeline.register import RigidTransform, TrackerRegistration, model_tip
from pipeline.train import HybridRegressor, TrainConfig


@dataclass
class Case:
    """An estimator, how to make its training data and how to use it once fitted."""

    make: Callable[[], Estimator]
    data: Callable[[Any], tuple]  # campaign D → fit arguments
    use: Callable[[Estimator, Any], np.ndarray]  # (fitted estimator, D) → an array to compare


def _clock_data(_d) -> tuple:
    rng = np.random.default_rng(0)
    host = 10**18 + np.cumsum(rng.integers(900_000, 1_100_000, 4000))  # ~1 kHz for 4 s
    ticks = ((host - host[0]) * (1 + 30e-6) // 1_000_000).astype(np.int64) + 5000  # 30 ppm fast, ms ticks
    return ticks, host + rng.exponential(2e5, host.size).astype(np.int64)


def _static_points(_d) -> tuple:
    """Static points of the VSL arm seen by a tracker 0.3 m off its base, turned 0.2 rad about z."""
    robot = load_robot("vsl")
    rng = np.random.default_rng(1)
    n = 40
    q = np.column_stack([rng.uniform(-0.8, 0.8, n), rng.uniform(0.2, 1.2, n), rng.uniform(-1.6, -0.4, n)])
    p = rng.uniform(0.5e5, 2.5e5, (n, 2))
    c, s = np.cos(0.2), np.sin(0.2)
    base_to_tracker = RigidTransform(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.array([0.3, 0.0, -0.1]))
    x = base_to_tracker.apply(model_tip(robot, q, p, np.zeros(n)))
    cols = {"stepper_position_0": q[:, 0], "servo_position_0": q[:, 1], "servo_position_1": q[:, 2]}
    cols |= {f"pressure_{k}": p[:, k] for k in range(2)} | {
        f"tracker_position_{k}": x[:, k] for k in range(3)
    }
    return (pd.DataFrame(cols | {"payload_kg": np.zeros(n)}),)


def _train_rows(d) -> tuple:
    return (B.part_of(d, "split_random", "train"),)


def _baseline(name: str, direction: str) -> B.Baseline:
    est = B.BASELINES[name](direction=direction)
    return est.set_params(max_iter=10) if name == "gbr" else est  # a few trees: the contract, not accuracy


def _net(direction: str) -> HybridRegressor:
    return HybridRegressor(TrainConfig(preset(direction, "small-residual"), max_epochs=3, seed=2), threads=1)


CASES = {
    "clock": Case(lambda: ClockModel(tick_s=1e-3), _clock_data, lambda e, d: e.predict(_clock_data(d)[0])),
    "registration": Case(
        lambda: TrackerRegistration(load_robot("vsl")),
        _static_points,
        lambda e, d: e.to_base(_static_points(d)[0].filter(like="tracker_position").to_numpy()),
    ),
    **{
        f"{name}-{direction}": Case(
            (lambda n=name, di=direction: _baseline(n, di)),
            _train_rows,
            lambda e, d: e.predict(B.part_of(d, "split_random", "test")),
        )
        for name in B.BASELINES
        for direction in B.DIRECTIONS
    },
    **{
        f"hybrid-{direction}": Case(
            (lambda di=direction: _net(di)),
            lambda d: (d,),  # the whole of D: the net takes its train rows and stops early on val
            lambda e, d: e.predict(B.part_of(d, "split_random", "test")),
        )
        for direction in ("forward", "inverse")
    },
}


@pytest.fixture(scope="module")
def data(campaign_dataset):
    return campaign_dataset[2]


@pytest.fixture(params=sorted(CASES), scope="module")
def case(request) -> Case:
    return CASES[request.param]


@pytest.fixture(scope="module")
def fitted(case, data):
    """Two estimators fitted alike (same parameters and seed) and what each gives."""
    a, b = case.make(), case.make()
    assert a.fit(*case.data(data)) is a  # fit returns self
    b.fit(*case.data(data))
    return a, case.use(a, data), case.use(b, data)


def test_the_constructor_only_stores_its_parameters(case):
    est = case.make()
    assert isinstance(est, Estimator)
    params = est.get_params(deep=False)
    assert params, "an estimator has parameters"
    assert est.fitted_attributes() == []  # nothing learned in the constructor
    assert not [k for k in vars(est) if k.endswith("_")]
    assert type(est)(**params).get_params(deep=False).keys() == params.keys()


def test_use_before_fit_raises_not_fitted(case, data):
    with pytest.raises(NotFittedError):
        case.use(case.make(), data)


def test_fit_learns_underscored_attributes_and_is_deterministic(fitted):
    est, first, second = fitted
    learned = est.fitted_attributes()
    assert learned and all(k.endswith("_") for k in learned)
    np.testing.assert_array_equal(first, second)  # same parameters and seed, same result
    assert np.isfinite(first).mean() > 0.9


def test_clone_is_a_fresh_estimator_with_the_same_parameters(fitted):
    est = fitted[0]
    copy = clone(est)
    assert copy is not est and copy.fitted_attributes() == []
    assert copy.get_params(deep=False).keys() == est.get_params(deep=False).keys()
    name = next(iter(copy.get_params(deep=False)))
    assert copy.set_params(**{name: copy.get_params(deep=False)[name]}) is copy


def test_a_trained_network_round_trips_through_the_registry(tmp_path, data):
    from pipeline import registry

    est = _net("forward").fit(data)
    assert est.history_.best_epoch >= 0
    version = registry.model_version("v1", est.config)
    path = registry.save_model(tmp_path, "forward", version, est.net_, {"train_config": est.config.to_dict()})
    loaded, _ = registry.load_model(path)
    test = B.part_of(data, "split_random", "test")
    x = test[list(est.config.net.inputs)].to_numpy(float)
    np.testing.assert_array_equal(loaded.predict(x), est.predict(test))


def test_a_fitted_registration_s_summary_is_json():
    import json

    rows = _static_points(None)[0]
    assert json.loads(json.dumps(TrackerRegistration(load_robot("vsl")).fit(rows).summary()))["points"] == 40
