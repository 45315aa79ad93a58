"""models.hybrid: the paper's networks and our variants (shapes, scaler, residual start, ensembles, I/O)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from models.errors import NotFittedError
from models.hybrid import FORWARD_INPUTS, INVERSE_INPUTS, PRESETS, HybridNet, NetConfig, preset


def _data(n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Raw-unit inputs (fk in m, p in Pa, i in A) and targets near the model columns."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(0.0, 0.3, (n, 3))
    x = np.column_stack([model, rng.uniform(5e4, 2e5, (n, 2)), rng.uniform(0.1, 0.6, (n, 2))])
    return x, model + rng.normal(0, 2e-3, (n, 3))


def test_presets_and_config_round_trip():
    assert preset("forward", "paper").hidden == (64, 256, 1024, 1024, 256, 64)
    assert not preset("inverse", "paper").residual and preset("inverse", "residual").residual
    assert preset("forward", "ensemble-small-residual").ensemble == 5
    for key, cfg in PRESETS.items():
        assert key == f"{cfg.direction}-{cfg.name}"
        assert NetConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert NetConfig("forward").inputs == FORWARD_INPUTS and NetConfig("inverse").inputs == INVERSE_INPUTS
    with pytest.raises(KeyError, match="no preset"):
        preset("forward", "huge")
    with pytest.raises(ValueError, match="direction"):
        NetConfig("sideways")  # type: ignore[arg-type]


def test_paper_architecture_and_shapes():
    net = HybridNet(preset("forward", "paper"))
    widths = [m.out_features for m in net.members[0] if isinstance(m, torch.nn.Linear)]
    assert widths == [64, 256, 1024, 1024, 256, 64, 3]
    assert sum(isinstance(m, torch.nn.ReLU) for m in net.members[0]) == 6
    x, y = _data()
    net.fit_scaler(x, y)
    for dtype in (torch.float32, torch.float64):
        out = net(torch.tensor(x, dtype=dtype))
        assert out.shape == (len(x), 3) and out.dtype == dtype
    assert net.predict(x).shape == (len(x), 3)


def test_unfitted_net_refuses_and_scaler_is_fitted_on_given_rows():
    net = HybridNet(preset("forward", "small-residual"))
    with pytest.raises(NotFittedError, match="fit_scaler"):
        net.predict(np.zeros((2, 7)))
    x, y = _data()
    net.fit_scaler(x, y)
    np.testing.assert_allclose(net.in_mean.numpy(), x.mean(0), rtol=1e-6)
    np.testing.assert_allclose(net.in_std.numpy(), x.std(0, ddof=1), rtol=1e-5)
    assert np.all(net.out_mean.numpy() == 0)  # residual nets scale the correction about zero
    np.testing.assert_allclose(net.out_std.numpy(), np.sqrt(((y - x[:, :3]) ** 2).mean(0)), rtol=1e-5)


@pytest.mark.parametrize("name", ["residual", "small-residual", "ensemble-small-residual"])
@pytest.mark.parametrize("direction", ["forward", "inverse"])
def test_untrained_residual_net_is_the_model(direction, name):
    torch.manual_seed(1)
    net = HybridNet(preset(direction, name))
    x, y = _data()
    net.fit_scaler(x, y)
    assert np.array_equal(net.predict(x), x[:, :3])  # zero last layer: exactly the model column
    assert np.all(net.predict_std(x) == 0)


def test_ensemble_members_differ():
    torch.manual_seed(0)
    net = HybridNet(NetConfig("forward", (16, 16), residual=False, ensemble=3, name="e3"))
    x, y = _data()
    net.fit_scaler(x, y)
    std = net.predict_std(x)
    assert std.shape == (len(x), 3) and np.all(std > 0)
    members = net.member_outputs(torch.tensor(x)).detach().numpy()
    np.testing.assert_allclose(net.predict(x), members.mean(0), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("key", ["forward-paper", "inverse-ensemble-small-residual"])
def test_from_state_round_trip_through_safetensors(tmp_path, key):
    torch.manual_seed(2)
    cfg = PRESETS[key]
    net = HybridNet(cfg)
    x, y = _data()
    net.fit_scaler(x, y)
    with torch.no_grad():  # move the zero last layers so the round trip checks real weights
        for p in net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    state = net.state_dict()
    assert all(isinstance(v, torch.Tensor) for v in state.values())
    save_file(state, tmp_path / "w.safetensors")
    back = HybridNet.from_state(NetConfig.from_dict(cfg.to_dict()), load_file(tmp_path / "w.safetensors"))
    assert np.array_equal(back.predict(x), net.predict(x))
    assert np.array_equal(back.predict_std(x), net.predict_std(x))
    with pytest.raises(RuntimeError):
        HybridNet.from_state(preset(cfg.direction, "small-residual"), state)  # wrong shapes
