"""Model integrity: a version whose files do not match its card is damaged; every command says so in one line.

The matrix: `vslab models list / show / compare`, `vslab simulate experiment2 --inverse-model` and `vslab run
experiment2 --plan …/hybrid --inverse-model` × a damaged inverse model beside a good forward one (weights with
a few bytes flipped — the case measured in issue 14, which loaded silently and commanded 2e35 rad —,
truncated, missing; the TorchScript export flipped or missing; the card with its net edited, its weights hash
edited, truncated, empty, random bytes, missing, without its file hashes or its own, a JSON list, another
version's card). Each cell checks the exit status, the one `error:` line (`models list`: one `warning:` line,
the damaged one listed as damaged and the good one as usual), that it names the damaged file, that nothing
says "Traceback", that the lab's files are unchanged and that `simulate` and `run` started nothing (no
sessions folder, no rig). Then: the good model in the loop, unknown, ambiguous and malformed versions, a
forward model given as the inverse one, and the loader itself (hashes, non-finite weights, the card's own
hash).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file
from typer.testing import CliRunner

from models.hybrid import HybridNet, NetConfig
from pipeline import model_store
from vslab.cli import app

runner = CliRunner()
INVERSE = ("inverse-tiny", "1a2b3c4d5e6f7a8b")  # the model the matrix damages
FORWARD = ("forward-tiny", "9f8e7d6c5b4a3f2e")  # a good one beside it


def _net(direction: str, seed: int) -> HybridNet:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    x = np.column_stack(
        [rng.uniform(-1, 1, (64, 3)), rng.uniform(5e4, 2e5, (64, 2)), rng.uniform(0, 1, (64, 2))]
    )
    net = HybridNet(NetConfig(direction, (8, 8), True, 1, "tiny"))
    return net.fit_scaler(x, x[:, :3] + rng.normal(0, 1e-3, (64, 3)))


def _card(direction: str) -> dict:
    net = {"direction": direction, "hidden": [8, 8], "residual": True, "ensemble": 1, "name": "tiny"}
    train = {"net": net, "seed": 0, "split": "split_random"}
    metrics = {"tip_mean_mm": 1.5, "tip_p95_mm": 3.0}
    return {"dataset": {"name": "campaign", "version": "0123abcd"}, "train_config": train, "metrics": metrics}


@pytest.fixture(scope="module")
def good_lab(tmp_path_factory) -> Path:
    """A lab with a tiny inverse and a tiny forward model, saved in the model store (hashes on cards)."""
    lab = tmp_path_factory.mktemp("models-lab")
    for (name, version), direction, seed in ((INVERSE, "inverse", 1), (FORWARD, "forward", 2)):
        model_store.save_model(lab / "models", name, version, _net(direction, seed), _card(direction))
    return lab


# ------------------------------------------------------------------------------------------ the damage
def _flip(path: Path, at: float = 0.6, n: int = 4) -> None:
    """XOR ``n`` bytes at a fraction ``at`` of the file (in a safetensors file: inside the tensors)."""
    data = bytearray(path.read_bytes())
    k = int(len(data) * at)
    for i in range(k, k + n):
        data[i] ^= 0x5A
    path.write_bytes(bytes(data))


def _edit_card(path: Path, edit) -> None:
    card = json.loads(path.read_text())
    edit(card)
    path.write_text(json.dumps(card, indent=1))


def _set_weights_hash(card: dict) -> None:
    card["files"][model_store.WEIGHTS] = "0" * 64


def _foreign_card(d: Path) -> None:
    shutil.copy(d.parents[1] / FORWARD[0] / FORWARD[1] / model_store.CARD, d / model_store.CARD)


def _halve(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


W, E, X, C = model_store.WEIGHTS, model_store.EXPORT, model_store.ONNX, model_store.CARD
DAMAGE = {  # name: (what it does to the model folder, the file the error must name)
    "weights-flipped": (lambda d: _flip(d / W), W),
    "weights-truncated": (lambda d: _halve(d / W), W),
    "weights-missing": (lambda d: (d / W).unlink(), W),
    "export-flipped": (lambda d: _flip(d / E), E),
    "export-missing": (lambda d: (d / E).unlink(), E),
    "onnx-flipped": (lambda d: _flip(d / X), X),
    "onnx-missing": (lambda d: (d / X).unlink(), X),
    "card-net-edited": (lambda d: _edit_card(d / C, lambda c: c["net"].update(residual=False)), C),
    "card-hash-edited": (lambda d: _edit_card(d / C, _set_weights_hash), C),
    "card-truncated": (lambda d: _halve(d / C), C),
    "card-empty": (lambda d: (d / C).write_bytes(b""), C),
    "card-random": (lambda d: (d / C).write_bytes(np.random.default_rng(3).bytes(700)), C),
    "card-missing": (lambda d: (d / C).unlink(), C),
    "card-no-hashes": (lambda d: _edit_card(d / C, lambda c: c.pop("files")), C),
    "card-no-own-hash": (lambda d: _edit_card(d / C, lambda c: c.pop("card_sha256")), C),  # an older card
    "card-a-list": (lambda d: (d / C).write_text("[1, 2, 3]\n"), C),
    "card-of-another": (_foreign_card, C),
}
COMMANDS = ("list", "show", "compare", "simulate", "run")


def _lab(tmp_path: Path, good_lab: Path, damage: str | None) -> Path:
    lab = tmp_path / "lab"
    shutil.copytree(good_lab, lab)
    if damage:
        DAMAGE[damage][0](lab / "models" / INVERSE[0] / INVERSE[1])
    return lab


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def _lines(output: str, prefix: str) -> list[str]:
    return [ln for ln in output.splitlines() if ln.startswith(prefix)]


def _invoke(lab: Path, *args: str):
    return runner.invoke(app, ["--lab", str(lab), "--quiet", *args])


ARGS = {
    "list": ["models", "list"],
    "show": ["models", "show", INVERSE[1][:6]],
    "compare": ["models", "compare", FORWARD[1], INVERSE[1]],
    "simulate": ["simulate", "experiment2", "--inverse-model", INVERSE[1]],
    "run": ["run", "experiment2", "--plan", "experiment2/curve/vsl-1.5bar/25g/hybrid", "--rig",
            "--inverse-model", INVERSE[1]],
}  # fmt: skip


# ------------------------------------------------------------------------------------------ the matrix
@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_model_gets_one_clear_line(good_lab, tmp_path, damage, command):
    lab = _lab(tmp_path, good_lab, damage)
    before = _hashes(lab)
    result = _invoke(lab, *ARGS[command])
    out = result.output
    assert "Traceback" not in out, out
    assert result.exception is None or isinstance(result.exception, SystemExit), (result.exception, out)
    errors, warnings = _lines(out, "error:"), _lines(out, "warning:")
    file = DAMAGE[damage][1]
    if command == "list":  # listed as damaged, with why; the good one as usual
        assert result.exit_code == 0, out
        assert not errors and len(warnings) == 1, out
        assert INVERSE[1] in warnings[0] and "damaged" in warnings[0] and file in warnings[0], out
        assert "damag" in out.split(INVERSE[1])[1].splitlines()[0], out  # its table row (80 columns) says so
        assert FORWARD[1] in out and "1.50" in out, out
    else:
        assert result.exit_code == 2, out
        assert len(errors) == 1 and not warnings, out
        assert file in errors[0] and INVERSE[1] in errors[0], out
        assert "damaged" in errors[0], out
    assert _hashes(lab) == before, f"{command} changed the lab's files"
    started = [p for p in ("sessions", "rig") if (lab / p).exists()]
    assert not started, f"{started} made before the model was checked"


def test_the_good_lab_lists_shows_and_compares(good_lab, tmp_path):
    lab = _lab(tmp_path, good_lab, None)
    result = _invoke(lab, "models", "list")
    assert result.exit_code == 0 and not _lines(result.output, "warning:"), result.output
    assert INVERSE[1] in result.output and FORWARD[1] in result.output
    for args in (ARGS["show"], ARGS["compare"]):
        result = _invoke(lab, *args)
        assert result.exit_code == 0 and "Traceback" not in result.output, result.output
    assert model_store.check_model(lab / "models" / INVERSE[0] / INVERSE[1])["version"] == INVERSE[1]


def test_a_good_inverse_model_runs_in_the_loop(good_lab, tmp_path):
    """The same command with the model whole: checked, loaded, and Experiment 2's hybrid plan runs with it."""
    lab = _lab(tmp_path, good_lab, None)
    small = ["cases=[{payload_g: 25, pressure_bar: 1.5}]", "commands=[hybrid]", "rigid_arm=false",
             "repetitions=1", "points_per_segment=5", "settle_s=0.5", "rest_s=0.2"]  # fmt: skip
    args = [*ARGS["simulate"], *(a for s in small for a in ("--set", s))]
    result = runner.invoke(app, ["--lab", str(lab), *args])
    assert result.exit_code == 0, result.output
    assert "1 sessions written" in result.output and "inverse model in the loop" in result.output


@pytest.mark.parametrize(
    ("version", "says"),
    [
        ("zzzz", "no model version 'zzzz'"),
        ("0000", "no model version '0000'"),
        ("*", "is not a model version"),
        ("../inverse-tiny", "is not a model version"),
        ("", "is not a model version"),
    ],
)
@pytest.mark.parametrize("command", ["show", "simulate", "compare", "run"])
def test_unknown_and_malformed_versions(good_lab, tmp_path, version, says, command):
    lab = _lab(tmp_path, good_lab, None)
    args = {"show": ["models", "show", version], "compare": ["models", "compare", FORWARD[1], version],
            "simulate": ["simulate", "experiment2", "--inverse-model", version],
            "run": ["run", "experiment1", "--rig", "--inverse-model", version]}[command]  # fmt: skip
    result = _invoke(lab, *args)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    (error,) = _lines(result.output, "error:")
    assert says in error, result.output
    assert not (lab / "sessions").exists()


def test_an_ambiguous_prefix_and_a_forward_model_in_the_loop(good_lab, tmp_path):
    lab = _lab(tmp_path, good_lab, None)
    shutil.copytree(
        lab / "models" / INVERSE[0] / INVERSE[1], lab / "models" / INVERSE[0] / "1a2b000000000000"
    )
    result = _invoke(lab, "models", "show", "1a2b")
    assert result.exit_code == 2 and "ambiguous" in _lines(result.output, "error:")[0], result.output
    result = _invoke(lab, "simulate", "experiment2", "--inverse-model", FORWARD[1])
    (error,) = _lines(result.output, "error:")
    assert result.exit_code == 2 and "a forward model" in error, result.output
    assert not (lab / "sessions").exists()


def test_list_goes_on_past_several_damaged_models(good_lab, tmp_path):
    lab = _lab(tmp_path, good_lab, "weights-flipped")
    other = lab / "models" / "inverse-tiny" / "ffff000000000000"
    shutil.copytree(good_lab / "models" / INVERSE[0] / INVERSE[1], other)
    (other / C).write_text("{")
    (lab / "models" / "stray-folder" / "0000").mkdir(parents=True)  # no card at all
    result = _invoke(lab, "models", "list")
    assert result.exit_code == 0 and "Traceback" not in result.output, result.output
    warnings = _lines(result.output, "warning:")
    assert len(warnings) == 3, result.output
    assert any("ffff000000000000" in w and "not valid JSON" in w for w in warnings), result.output
    assert any("stray-folder/0000" in w and "card.json: missing" in w for w in warnings), result.output
    assert FORWARD[1] in result.output


# ------------------------------------------------------------------------------------------ the loader
def test_loading_checks_every_file_and_names_it(good_lab, tmp_path):
    lab = _lab(tmp_path, good_lab, None)
    path = lab / "models" / INVERSE[0] / INVERSE[1]
    model, card = model_store.load_model(path)
    assert card["version"] == INVERSE[1] and model.config.direction == "inverse"
    model_store.load_exported(path)
    model_store.load_onnx(path)
    _flip(path / W)
    for load in (
        model_store.load_model,
        model_store.load_exported,
        model_store.load_onnx,
        model_store.check_model,
    ):
        with pytest.raises(
            model_store.ModelIntegrityError, match=r"weights\.safetensors: not the bytes"
        ) as info:
            load(path)
        assert isinstance(info.value, ValueError) and info.value.file == W


def test_consistent_hashes_over_bad_tensors_still_do_not_load(good_lab, tmp_path):
    """Weights rewritten with NaNs (or of another net) and every hash updated to match: the hashes pass, the
    tensors are refused when the net is built."""
    lab = _lab(tmp_path, good_lab, None)
    path = lab / "models" / INVERSE[0] / INVERSE[1]
    net = _net("inverse", 1)
    state = {k: v.clone() for k, v in net.state_dict().items()}
    state["members.0.0.weight"][0, 0] = float("nan")
    for tensors, says in ((state, "non-finite"), (_net("inverse", 1).state_dict() | {"extra": torch.ones(1)},
                                                  "Unexpected key")):  # fmt: skip
        save_file({k: v.contiguous() for k, v in tensors.items()}, path / W)
        card = json.loads((path / C).read_text())
        card["files"][W] = model_store.file_sha256(path / W)
        card["card_sha256"] = model_store.card_digest(card)
        (path / C).write_text(json.dumps(card))
        assert model_store.check_model(path)  # the hashes agree …
        with pytest.raises(model_store.ModelIntegrityError, match=says):  # … the tensors do not
            model_store.load_model(path)


def test_a_card_edited_by_hand_is_caught_even_when_it_stays_valid_json(good_lab, tmp_path):
    lab = _lab(tmp_path, good_lab, None)
    path = lab / "models" / INVERSE[0] / INVERSE[1]
    text = (path / C).read_text()
    (path / C).write_text(text.replace('"tip_mean_mm": 1.5', '"tip_mean_mm": 0.5'))
    with pytest.raises(model_store.ModelIntegrityError, match="card_sha256 does not match"):
        model_store.load_card(path)
    (path / C).write_text(json.dumps(json.loads(text), indent=4, sort_keys=True))  # layout is not content
    assert model_store.load_card(path)["version"] == INVERSE[1]


@pytest.mark.slow
def test_train_refuses_to_count_a_damaged_version_as_trained(tmp_path, campaign_dataset):
    """`vslab train` skips the versions it has; one whose files were damaged is an error naming the file,
    not an "existing" model (it would never be trained again)."""
    import yaml

    src, _, _ = campaign_dataset
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "datasets").symlink_to(src / "datasets")
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({"models": [{"direction": "inverse", "preset": "small-residual",
                                                "hidden": [8]}], "datasets": ["campaign"],
                                    "train": {"max_epochs": 1, "batch_size": 256}}))  # fmt: skip
    args = ["--lab", str(lab), "--quiet", "train", "--grid", str(grid), "--workers", "1"]
    assert runner.invoke(app, args).exit_code == 0
    (version,) = (lab / "models" / "inverse-small-residual").iterdir()
    _flip(version / W)
    before = _hashes(lab / "models")
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    (error,) = _lines(result.output, "error:")
    assert W in error and version.name in error and "damaged" in error, result.output
    assert _hashes(lab / "models") == before
