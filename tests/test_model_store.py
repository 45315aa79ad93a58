"""Model store, grid training and `vslab train` / `vslab models`: content-addressed versions that load
without unpickling, TorchScript exports that agree with the module, grids that never train a version twice."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from models.hybrid import NetConfig
from pipeline import model_store
from pipeline.exports import OnnxModel, quantized
from pipeline.grid import GridError, load_grid, run_grid
from pipeline.lab import Lab
from pipeline.train import TrainConfig, train

TINY = {"hidden": [16, 16]}


def _config(direction="inverse", seed=0, residual=True, **kw) -> TrainConfig:
    net = NetConfig(direction, (16, 16), residual, 1, "tiny")
    return TrainConfig(net=net, max_epochs=3, patience=2, batch_size=64, seed=seed, **kw)


@pytest.fixture
def lab(tmp_path, campaign_dataset):
    """A fresh lab sharing the session's campaign dataset (read-only)."""
    src, _, _ = campaign_dataset
    (tmp_path / "datasets").symlink_to(src / "datasets")
    return tmp_path


@pytest.fixture(scope="module")
def trained(campaign_dataset):
    """(config, version, TrainResult) of a tiny inverse net on the campaign dataset."""
    _, version, data = campaign_dataset
    config = _config()
    return config, model_store.model_version(version, config), train(data, config, threads=1)


def _inputs(data, config) -> np.ndarray:
    x = data[list(config.net.inputs)].to_numpy(float)
    return x[np.isfinite(x).all(1)]


def test_round_trip_gives_identical_predictions_without_unpickling(
    tmp_path, campaign_dataset, trained, monkeypatch
):
    _, dataset_version, data = campaign_dataset
    config, version, result = trained
    card = {"dataset": {"name": "campaign", "version": dataset_version}, "train_config": config.to_dict()}
    path = model_store.save_model(tmp_path, "inverse-tiny", version, result.model, card)
    assert sorted(p.name for p in path.iterdir()) == ["card.json", "export", "weights.safetensors"]
    assert sorted(p.name for p in (path / "export").iterdir()) == ["model.onnx", "model.ts"]
    assert [p.name for p in tmp_path.joinpath("inverse-tiny").iterdir()] == [version]  # no temp dir left

    def refuse(*args, **kwargs):
        raise AssertionError("loading a model must not unpickle")

    for target, attr in ((torch, "load"), (pickle, "load"), (pickle, "loads"), (pickle, "Unpickler")):
        monkeypatch.setattr(target, attr, refuse)
    model, loaded = model_store.load_model(path)
    x = _inputs(data, config)
    np.testing.assert_array_equal(model.predict(x), result.model.predict(x))
    assert loaded["version"] == version and loaded["dataset"]["version"] == dataset_version
    assert loaded["net"] == config.net.to_dict() and loaded["torch"] == torch.__version__
    assert {"code_version", "created", "files"} <= set(loaded)


def test_export_gives_the_module_outputs(tmp_path, campaign_dataset, trained):
    _, _, data = campaign_dataset
    config, version, result = trained
    path = model_store.save_model(
        tmp_path, "inverse-tiny", version, result.model, {"train_config": config.to_dict()}
    )
    exported = model_store.load_exported(path)
    x = _inputs(data, config)
    with torch.no_grad():
        out = exported(torch.as_tensor(x, dtype=torch.float64))
        one = exported(torch.as_tensor(x[:1], dtype=torch.float64))
    assert out.dtype == torch.float64 and out.shape == (len(x), 3)
    np.testing.assert_allclose(out.numpy(), result.model.predict(x), rtol=0, atol=1e-9)
    np.testing.assert_allclose(one.numpy(), result.model.predict(x[:1]), rtol=0, atol=1e-9)


@pytest.mark.parametrize("preset_name", ["paper", "small-residual"])
def test_the_onnx_export_run_by_onnx_runtime_is_the_network(tmp_path, campaign_dataset, preset_name):
    """ONNX Runtime (the in-loop executor) gives the torch network's outputs on the test split: max abs
    difference ≤ 1e-5 (rad), one sample at a time as the loop calls it and as a batch."""
    import dataclasses

    from models.hybrid import preset

    _, dataset_version, data = campaign_dataset
    net = dataclasses.replace(preset("inverse", preset_name))
    config = TrainConfig(net=net, max_epochs=2, patience=2, batch_size=64, seed=0)
    result = train(data, config, threads=1)
    version = model_store.model_version(dataset_version, config)
    path = model_store.save_model(tmp_path, f"inverse-{preset_name}", version, result.model,
                               {"train_config": config.to_dict()})  # fmt: skip
    onnx = model_store.load_onnx(path)
    x = _inputs(data[data[config.split] == "test"], config)
    assert len(x) > 50
    reference = result.model.predict(x)
    assert np.abs(onnx.predict(x) - reference).max() <= 1e-5
    single = np.concatenate([onnx.predict(x[k : k + 1]) for k in range(len(x))])
    assert np.abs(single - reference).max() <= 1e-5
    assert onnx.predict(x).dtype == np.float64
    # the int8 graph bench/train.py times: a quarter of the weights' bytes, the same interface, near the
    # network (not within 1e-5: its error on the test split is the bench's to report)
    data = (path / model_store.ONNX).read_bytes()
    int8 = quantized(data)
    assert quantized(data) == int8  # deterministic: the same bytes for the same graph
    if preset_name == "paper":
        assert len(int8) < 0.35 * len(data)
    assert np.abs(OnnxModel(int8).predict(x) - reference).max() < 0.1


def test_a_model_saved_before_the_onnx_export_loads_but_has_no_onnx(tmp_path, trained):
    config, version, result = trained
    path = model_store.save_model(tmp_path, "m", version, result.model, {"train_config": config.to_dict()})
    card = model_store.load_card(path)
    del card["files"][model_store.ONNX]
    card["card_sha256"] = model_store.card_digest(card)
    (path / model_store.CARD).write_text(json.dumps(card, indent=1))
    (path / model_store.ONNX).unlink()
    model_store.load_model(path)  # weights and TorchScript: as they were
    with pytest.raises(model_store.ModelIntegrityError, match="saved before vslab exported ONNX"):
        model_store.load_onnx(path)


def test_an_existing_version_is_never_overwritten(tmp_path, trained):
    config, version, result = trained
    path = model_store.save_model(tmp_path, "m", version, result.model, {"train_config": config.to_dict()})
    before = (path / "weights.safetensors").read_bytes()
    with pytest.raises(FileExistsError):
        model_store.save_model(tmp_path, "m", version, HybridLike(config), {"train_config": config.to_dict()})
    assert (path / "weights.safetensors").read_bytes() == before
    assert [p.name for p in (tmp_path / "m").iterdir()] == [version]


def HybridLike(config):
    from models.hybrid import HybridNet

    return HybridNet(config.net).fit_scaler(np.random.default_rng(0).normal(size=(8, 7)), np.zeros((8, 3)))


def test_version_id_is_stable_and_content_derived():
    a = model_store.model_version("d1", _config())
    assert (
        a
        == model_store.model_version("d1", _config())
        == model_store.model_version("d1", _config().to_dict())
    )
    assert len(a) == 16
    assert a != model_store.model_version("d2", _config())
    assert a != model_store.model_version("d1", _config(seed=1))
    assert a != model_store.model_version("d1", _config(lr=2e-3))


def test_training_twice_gives_the_same_version_and_weights(campaign_dataset, trained):
    _, dataset_version, data = campaign_dataset
    _, version, first = trained
    again = train(data, _config(), threads=1)
    assert model_store.model_version(dataset_version, again.config) == version
    a, b = first.model.state_dict(), again.model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _grid(tmp_path, **extra) -> dict:
    grid = {
        "models": [{"direction": "forward", "preset": "small-residual", **TINY},
                   {"direction": "inverse", "preset": "paper", **TINY}],
        "datasets": ["campaign"], "splits": ["split_random"], "seeds": [0],
        "train": {"max_epochs": 2, "patience": 2, "batch_size": 128},
    } | extra  # fmt: skip
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(grid))
    return path


def test_grid_trains_each_version_once(lab, monkeypatch):
    grid = load_grid(_grid(lab))
    seen = []
    first = run_grid(Lab(lab), grid, workers=1, progress=lambda done, total, s: seen.append((done, total)))
    assert [r["status"] for r in first] == ["trained", "trained"] and seen[-1] == (2, 2)
    assert all(np.isfinite(r["test_mean_mm"]) for r in first)
    assert {r["name"] for r in first} == {"forward-small-residual", "inverse-paper"}

    import pipeline.train

    monkeypatch.setattr(pipeline.train, "train", lambda *a, **k: pytest.fail("trained an existing version"))
    second = run_grid(Lab(lab), grid, workers=1)
    assert [r["status"] for r in second] == ["existing", "existing"]
    assert [r["version"] for r in second] == [r["version"] for r in first]
    assert [r["test_mean_mm"] for r in second] == pytest.approx([r["test_mean_mm"] for r in first])
    listed = model_store.list_models(lab / "models")
    assert sorted(r["version"] for r in listed) == sorted(r["version"] for r in first)


def test_grid_errors_name_what_is_wrong(lab):
    with pytest.raises(GridError, match="max_epoch"):
        load_grid(_grid(lab), {"max_epoch": 3})
    with pytest.raises(GridError, match="no dataset 'nope'"):
        run_grid(Lab(lab), load_grid(_grid(lab, datasets=["nope"])))
    with pytest.raises(GridError, match="no preset"):
        run_grid(Lab(lab), load_grid(_grid(lab, models=[{"direction": "inverse", "preset": "huge"}])))


def test_a_grid_tags_its_tagged_models_once_every_job_is_done(lab):
    """`tag:` on a grid's model: that network gets the tag in the lab's models (the main job's grid tags what
    the figures and Experiment 2 use); a tag that cannot name one network is refused before any training."""
    models = [{"direction": "forward", "preset": "small-residual", "tag": "fwd", **TINY},
              {"direction": "inverse", "preset": "paper", **TINY}]  # fmt: skip
    results = run_grid(Lab(lab), load_grid(_grid(lab, models=models)), workers=1)
    assert [r.get("tag") for r in results] == ["fwd", None]
    assert Lab(lab).models.tags() == {"fwd": results[0]["version"]}
    assert Lab(lab).models.find("fwd").name == results[0]["version"]
    refused = {
        "repeat one": {"models": [models[0], {**models[1], "tag": "fwd"}]},
        "one split and one seed": {"models": models, "seeds": [0, 1]},
        "expected a tag name": {"models": [{**models[0], "tag": "Fwd!"}]},
    }
    for says, grid in refused.items():
        with pytest.raises(GridError, match=says):
            run_grid(Lab(lab), load_grid(_grid(lab, **grid)), workers=1)


def test_the_main_jobs_grid_tags_the_networks_the_figures_and_experiment2_find():
    from pathlib import Path

    from pipeline.model_store import LAB_TAGS

    grid = load_grid(Path(__file__).resolve().parents[1] / "configs" / "train" / "lab.yaml")
    assert sorted(m["tag"] for m in grid["models"] if "tag" in m) == sorted(LAB_TAGS)


@pytest.mark.slow
def test_cli_train_list_show_compare(lab):
    from vslab.cli import app

    runner = CliRunner()
    grid = _grid(
        lab,
        models=[{"direction": "inverse", "preset": "small-residual", **TINY}],
        splits=["split_random", "split_group"],
    )
    args = ["--lab", str(lab), "--quiet"]
    train = [*args, "train", "--grid", str(grid), "--set", "max_epochs=1", "--workers", "2"]  # a process pool
    result = runner.invoke(app, train)
    assert result.exit_code == 0, result.output
    assert "2 trained, 0 existing" in result.output
    result = runner.invoke(app, train)
    assert "0 trained, 2 existing" in result.output, result.output
    versions = [r["version"] for r in model_store.list_models(lab / "models")]
    result = runner.invoke(app, [*args, "models", "list"])
    assert result.exit_code == 0 and all(v in result.output for v in versions), result.output
    result = runner.invoke(app, [*args, "models", "show", versions[0][:8]])
    assert result.exit_code == 0, result.output
    assert "tip_mean_mm" in result.output and "per cell" in result.output
    result = runner.invoke(app, [*args, "models", "compare", *versions])
    assert result.exit_code == 0 and "split_group" in result.output, result.output
    result = runner.invoke(app, [*args, "models", "show", "zzzz"])
    assert result.exit_code == 2 and "no model version 'zzzz'" in result.output
    result = runner.invoke(app, [*args, "train", "--grid", str(lab / "missing.yaml")])
    assert result.exit_code == 2 and "no grid file" in result.output and "Traceback" not in result.output
