"""pipeline.train: seeded, deterministic training of the hybrid nets on the twin campaign, and evaluation."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from models.hybrid import FORWARD_INPUTS, NetConfig, preset
from pipeline.train import TrainConfig, evaluate, evaluate_rigid, train

SMALL = preset("forward", "small-residual")


def _cfg(net: NetConfig = SMALL, **kw) -> TrainConfig:
    return TrainConfig(net, **{"max_epochs": 30, **kw})


def test_train_config_round_trip_and_checks():
    cfg = _cfg(preset("inverse", "paper"), split="split_group", seed=3)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="split"):
        _cfg(split="split_rnd")


def test_forward_residual_net_beats_the_rigid_model(campaign_dataset):
    _, _, data = campaign_dataset
    result = train(data, _cfg(), threads=2)
    rigid, net = evaluate_rigid(data, "forward"), evaluate(result.model, data)
    r, s = (f"{m['tip_mean_mm']:.3f}/{m['tip_p95_mm']:.3f}" for m in (rigid, net))
    print(f"\nforward test tip error, mean/p95 mm: rigid {r}, small-residual {s}")
    test = data[data["split_random"] == "test"]
    direct = np.linalg.norm(
        test[["fk_0", "fk_1", "fk_2"]].to_numpy() - test[["x_0", "x_1", "x_2"]].to_numpy(), axis=1
    )
    assert rigid["tip_mean_mm"] == pytest.approx(direct.mean() * 1e3) and rigid["n"] == net["n"] == len(test)
    assert net["tip_mean_mm"] < 0.5 * rigid["tip_mean_mm"]
    assert net["tip_median_mm"] <= net["tip_p95_mm"] <= net["tip_max_mm"]
    n_epochs = len(result.train_loss)
    assert len(result.val_loss) == len(result.val_error_mm) == n_epochs and 0 <= result.best_epoch < n_epochs
    assert result.val_loss[result.best_epoch] == min(result.val_loss)
    assert result.train_loss[-1] < result.train_loss[0] and result.epoch_time_s > 0
    cells = net["per_cell"]
    assert sum(c["n"] for c in cells) == net["n"]
    assert {c["payload_g"] for c in cells} <= {0, 25, 50, 75, 100}
    json.dumps(result.to_dict() | {"metrics": net})  # card-ready


def test_scaler_is_fitted_on_the_training_rows_only(campaign_dataset):
    _, _, data = campaign_dataset
    model = train(data, _cfg(max_epochs=1), threads=1).model
    x = data[list(FORWARD_INPUTS)].to_numpy(float)
    train_rows = (data["split_random"] == "train").to_numpy()
    np.testing.assert_allclose(model.in_mean.numpy(), x[train_rows].mean(0), rtol=1e-6)
    assert not np.allclose(model.in_mean.numpy(), x.mean(0), rtol=1e-6)
    np.testing.assert_allclose(model.in_std.numpy(), x[train_rows].std(0, ddof=1), rtol=1e-5)


def test_same_seed_same_weights_other_seed_other_weights(campaign_dataset):
    _, _, data = campaign_dataset
    before = (torch.are_deterministic_algorithms_enabled(), torch.get_num_threads())
    a, b, c = (train(data, _cfg(max_epochs=4, seed=s), threads=2).model.state_dict() for s in (5, 5, 6))
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    assert (torch.are_deterministic_algorithms_enabled(), torch.get_num_threads()) == before  # restored


def test_inverse_training_reports_joint_and_tip_errors(campaign_dataset):
    _, _, data = campaign_dataset
    result = train(
        data, _cfg(preset("inverse", "small-residual"), split="split_group", max_epochs=20), threads=2
    )
    m = evaluate(result.model, data, split="split_group")
    rigid = evaluate_rigid(data, "inverse", split="split_group")
    for key in ("joint_mean_mrad", "joint_p95_mrad", "tip_mean_mm", "tip_max_mm"):
        assert np.isfinite(m[key]) and np.isfinite(rigid[key])
    assert m["joint_mean_mrad"] < rigid["joint_mean_mrad"]
    assert {"joint_mrad_mean", "tip_mm_mean"} <= m["per_cell"][0].keys()


def test_trained_ensemble_has_a_spread(campaign_dataset):
    _, _, data = campaign_dataset
    model = train(data, _cfg(preset("forward", "ensemble-small-residual"), max_epochs=3), threads=2).model
    x = data[list(FORWARD_INPUTS)].to_numpy(float)[:50]
    std = model.predict_std(x)
    assert std.shape == (50, 3) and np.all(std > 0)


def test_a_large_net_gets_the_same_weights_on_every_core_as_on_one(campaign_dataset):
    """A grid trains each large net alone on every core (``pipeline.grid._rounds``) while its version does not
    name a thread count: the weights must not depend on it (deterministic algorithms, the same seed)."""
    from pipeline.grid import HEAVY_WEIGHTS, net_weights

    _, _, data = campaign_dataset
    net = NetConfig("forward", (256, 256, 256), True, 1, "large")
    assert net_weights(net) >= HEAVY_WEIGHTS
    config = TrainConfig(net, max_epochs=4, patience=4, seed=3)
    one, every = (train(data, config, threads=t).model.state_dict() for t in (1, max(2, os.cpu_count() or 1)))
    assert all(torch.equal(one[k], every[k]) for k in one)


def test_a_grid_trains_the_small_nets_side_by_side_then_each_large_one_alone():
    import concurrent.futures as cf

    from pipeline.build import InlineExecutor
    from pipeline.grid import _rounds

    def job(name: str) -> dict:
        return {"name": name, "config": TrainConfig(preset("forward", name)).to_dict()}

    todo = [job("small-residual"), job("paper"), job("ensemble-small-residual"), job("residual")]
    rounds = list(_rounds(todo, None, None, None))
    cores = os.cpu_count() or 1
    assert [[j["name"] for j in jobs] for jobs, _, _ in rounds] == [
        ["small-residual", "ensemble-small-residual"], ["paper"], ["residual"]]  # fmt: skip
    assert rounds[0][2] == 1 and all(t == cores and isinstance(e, InlineExecutor) for _, e, t in rounds[1:])
    for _, executor, _ in rounds:
        executor.shutdown()
    given = InlineExecutor()  # an executor, a worker or a thread count given: every job at once, as asked
    assert [(len(j), e, t) for j, e, t in _rounds(todo, given, None, 1)] == [(4, given, 1)]
    ((jobs, pool, threads),) = _rounds(todo, None, 2, None)
    assert len(jobs) == 4 and threads == max(1, cores // 2)
    assert isinstance(pool, cf.ProcessPoolExecutor)
    pool.shutdown()
