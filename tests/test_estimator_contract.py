"""One contract for every fitted thing (models/estimator.py, scikit-learn's): the clock fitter, the tracker
registrations (fitted and borrowed), every baseline and the hybrid networks, run through the same checks.

- the constructor only stores its parameters: ``get_params`` gives back what was passed, nothing learned;
- ``fit`` returns ``self`` and learns attributes ending in ``_``, none of which exist before;
- use before ``fit`` raises the one ``NotFittedError``;
- the same parameters and seed give the same result; ``clone`` / ``set_params`` make a fresh, equal one;
- what is saved comes back the same: a network through the registry, a registration through a dataset
  card, a baseline's parameters through JSON (the model store saves no baseline).
"""

from __future__ import annotations

import atexit
import functools
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch
from sklearn.base import clone

from models.errors import NotFittedError
from models.estimator import Estimator
from models.hybrid import HybridNet, preset
from models.robot import load_robot
from pipeline import baselines as B
from pipeline.clock import ClockFitter
from pipeline.damping_fit import VslDampingFit
from pipeline.popup_fit import PopupLinkFit
from pipeline.registration import FixedRegistration, RigidTransform, TrackerRegistration, model_tip
from pipeline.servo_fit import ServoFit
from pipeline.train import HybridRegressor, TrainConfig, train
from pipeline.twin_fit import VslStaticFit


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


C, S = np.cos(0.2), np.sin(0.2)
BASE_TO_TRACKER = RigidTransform(np.array([[C, -S, 0], [S, C, 0], [0, 0, 1]]), np.array([0.3, 0.0, -0.1]))


def _static_points(_d) -> tuple:
    """Static points of the VSL arm seen by a tracker 0.3 m off its base, turned 0.2 rad about z."""
    robot = load_robot("vsl")
    rng = np.random.default_rng(1)
    n = 40
    q = np.column_stack([rng.uniform(-0.8, 0.8, n), rng.uniform(0.2, 1.2, n), rng.uniform(-1.6, -0.4, n)])
    p = rng.uniform(0.5e5, 2.5e5, (n, 2))
    x = BASE_TO_TRACKER.apply(model_tip(robot, q, p, np.zeros(n)))
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


def _fine_tuned() -> HybridRegressor:
    """An inverse net fine-tuned from a pretrained one (``pipeline.pretrain``): here one whose scaler saw a
    made-up sample (the contract, not pretraining's worth)."""
    config = TrainConfig(preset("inverse", "small-residual"), max_epochs=3, seed=2)
    rng = np.random.default_rng(4)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(4)  # the made-up start's weights: the same at every call
        start = HybridNet(config.net).fit_scaler(rng.normal(size=(50, 7)), rng.normal(size=(50, 3)))
    return HybridRegressor(config, threads=1, pretrained=start)


def _link_tests(_d) -> tuple:
    """(static holds, taps) of the POPUP link tests, simulated once at three pressures (kept for the run)."""
    return _simulated_link_tests()


@functools.cache
def _simulated_link_tests() -> tuple:
    import tempfile

    from acquisition.recorder.sessions import SessionStore
    from pipeline.link_tests import impact_taps, static_holds
    from twin.runner import simulate_experiment

    root = Path(tempfile.mkdtemp(prefix="vslab-link-tests-"))
    atexit.register(shutil.rmtree, root, True)
    store = SessionStore(root / "sessions")
    small = {"pressures_kpa": [10, 30, 50]}
    quick = {"repetitions": 1, "settle_s": 1.2, "pressure_settle_s": 1.0}
    simulate_experiment("popup_static", store, seed=3, overrides=small | quick)
    simulate_experiment("popup_impact", store, seed=3, overrides=small | {"taps": 2, "record_s": 1.2})
    sessions = sorted((root / "sessions").iterdir())
    holds = pd.concat([static_holds(s) for s in sessions if "popup_static" in s.name], ignore_index=True)
    taps = pd.concat([impact_taps(s) for s in sessions if "popup_impact" in s.name], ignore_index=True)
    return holds, taps


def _to_base(est: Estimator, d) -> np.ndarray:
    return est.to_base(_static_points(d)[0].filter(like="tracker_position").to_numpy())


CASES = {
    "clock": Case(lambda: ClockFitter(tick_s=1e-3), _clock_data, lambda e, d: e.predict(_clock_data(d)[0])),
    "registration": Case(lambda: TrackerRegistration(load_robot("vsl")), _static_points, _to_base),
    "twin-fit-vsl": Case(
        lambda: VslStaticFit("vsl"), lambda d: (d,), lambda e, d: e.table()["value"].dropna().to_numpy()
    ),
    "twin-fit-damping": Case(  # 40 of the small campaign's moves made again on the papers' arm
        lambda: VslDampingFit(load_robot("vsl"), max_moves=40),
        lambda d: (MOVES[0], d),
        lambda e, d: e.table()[["value", "stderr"]].to_numpy(),
    ),
    "twin-fit-servos": Case(
        lambda: ServoFit("vsl"), lambda d: (d,), lambda e, d: e.table()[["value", "stderr"]].to_numpy()
    ),
    "twin-fit-popup": Case(
        lambda: PopupLinkFit("popup"), _link_tests, lambda e, d: e.table()["value"].dropna().to_numpy()
    ),
    "registration-borrowed": Case(
        lambda: FixedRegistration(BASE_TO_TRACKER.matrix().tolist(), "campaign@v1"), _static_points, _to_base
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
    "hybrid-inverse-fine-tuned": Case(
        _fine_tuned, lambda d: (d,), lambda e, d: e.predict(B.part_of(d, "split_random", "test"))
    ),
}


MOVES: list[pd.DataFrame] = []  # the small campaign's moves into its points (its dataset's moves table)


@pytest.fixture(scope="module")
def data(campaign_dataset):
    from pipeline.dataset_store import DatasetStore

    lab, version, d = campaign_dataset
    MOVES[:] = [DatasetStore(lab / "datasets").load("campaign", version, table="moves")[0]]
    return d


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
    again = type(est)(**params).get_params(deep=False)
    assert again.keys() == params.keys()
    assert all(again[k] is v for k, v in params.items())  # stored as given: no copy, no conversion


def test_use_before_fit_raises_not_fitted(case, data):
    with pytest.raises(NotFittedError):
        case.use(case.make(), data)


@pytest.mark.slow
def test_fit_learns_underscored_attributes_and_is_deterministic(fitted):
    est, first, second = fitted
    learned = est.fitted_attributes()
    assert learned and all(k.endswith("_") for k in learned)
    np.testing.assert_array_equal(first, second)  # same parameters and seed, same result
    assert np.isfinite(first).mean() > 0.9


def _comparable(params: dict) -> dict:
    """Parameters as values: a net (a fine-tuned net's start, which clone copies) by its weights."""
    return {
        k: {n: t.tolist() for n, t in v.state_dict().items()} if isinstance(v, torch.nn.Module) else v
        for k, v in params.items()
    }


def test_clone_is_a_fresh_estimator_with_the_same_parameters(fitted):
    est = fitted[0]
    copy = clone(est)
    assert copy is not est and copy.fitted_attributes() == []
    params = est.get_params(deep=False)
    assert _comparable(copy.get_params(deep=False)) == _comparable(params)
    name, other = next(iter(params)), object()
    assert copy.set_params(**{name: other}) is copy  # set_params only stores, as the constructor does
    assert copy.get_params(deep=False)[name] is other and est.get_params(deep=False)[name] is params[name]


def test_a_trained_network_round_trips_through_the_model_store(tmp_path, data):
    from pipeline import model_store

    est = _net("forward").fit(data)
    assert est.history_.best_epoch >= 0
    version = model_store.model_version("v1", est.config)
    path = model_store.save_model(
        tmp_path, "forward", version, est.net_, {"train_config": est.config.to_dict()}
    )
    loaded, _ = model_store.load_model(path)
    test = B.part_of(data, "split_random", "test")
    x = test[list(est.config.net.inputs)].to_numpy(float)
    np.testing.assert_array_equal(loaded.predict(x), est.predict(test))


def test_train_is_the_estimator_s_history(data):
    """``train`` is a convenience over ``HybridRegressor``: the same net and curves."""
    est, result = _net("inverse").fit(data), train(data, _net("inverse").config, threads=1)
    assert result.val_loss == est.history_.val_loss and result.best_epoch == est.history_.best_epoch
    for name, tensor in est.net_.state_dict().items():
        assert torch.equal(tensor, result.model.state_dict()[name]), name


def test_a_registration_round_trips_through_a_dataset_card():
    """A fitted registration's card (JSON) borrowed by another build maps points as the fitted one did."""
    rows = _static_points(None)[0]
    fitted = TrackerRegistration(load_robot("vsl")).fit(rows)
    card = json.loads(json.dumps(fitted.summary()))
    assert card["points"] == 40
    borrowed = FixedRegistration(card["base_to_tracker"], "campaign@v1").fit(rows.iloc[:0])
    x = rows.filter(like="tracker_position").to_numpy()
    np.testing.assert_allclose(borrowed.to_base(x), fitted.to_base(x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(borrowed.placement(), card["base_to_tracker"], rtol=0, atol=1e-15)
    assert json.loads(json.dumps(borrowed.summary()))["from_dataset"] == "campaign@v1"


def test_a_borrowed_registration_refuses_a_damaged_placement():
    with pytest.raises(ValueError, match="4×4"):
        FixedRegistration([[1.0, 0.0], [0.0, 1.0]], "campaign@v1").fit()


@pytest.mark.parametrize("name", ["rigid", "prbm", "knn"])
def test_a_baseline_s_parameters_round_trip_through_json(name, data):
    """What a baseline report records of it (``to_dict``) is JSON, and its parameters rebuild the same fit."""
    rows, test = B.part_of(data, "split_random", "train"), B.part_of(data, "split_random", "test")
    est = B.BASELINES[name](direction="forward").fit(rows)
    assert json.loads(json.dumps(est.to_dict()))["name"] == name
    params = {k: v for k, v in est.get_params(deep=False).items() if k != "robot"}
    again = type(est)(**json.loads(json.dumps(params))).fit(rows)
    np.testing.assert_array_equal(again.predict(test), est.predict(test))
