"""The JSON Schemas of the lab's YAML files (vslab/schemas.py, configs/schemas/): shipped and current, named
at the top of every file of configs/, every such file valid, and a wrong field refused by the schema as by
vslab.

(tests/test_schemas.py is the CDR message schemas' test: these are the editors' JSON Schemas.)
"""

from __future__ import annotations

import copy
import dataclasses
import json
import re
from collections.abc import Callable
from pathlib import Path

import jsonschema
import pytest
import yaml
from typer.testing import CliRunner

from acquisition.plans import popup_experiments
from acquisition.plans.experiment_files import EXPERIMENT_FILES, PARAMETERS
from acquisition.plans.experiments import (
    EXPERIMENT_DIR,
    ExperimentError,
    check_experiment,
    experiment2,
    load_experiment,
)
from models.robot import CONFIG_DIR, RobotDescriptionError, load_robot
from pipeline.grid_file import DATASET_PATTERN, PRESETS, SPLITS, TAG_PATTERN, GridFile, GridModel, TrainFields
from vslab.cli import app
from vslab.schemas import SCHEMAS, schema, schema_names, schema_text

CONFIGS = CONFIG_DIR.parent
SCHEMA_DIR = CONFIGS / "schemas"
HEADER = re.compile(r"# yaml-language-server: \$schema=(\.\./schemas/[\w.-]+\.schema\.json)")
YAMLS = sorted(p for folder in ("robots", "experiments", "train") for p in (CONFIGS / folder).glob("*.yaml"))
runner = CliRunner()


def validator(name: str) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(json.loads((SCHEMA_DIR / f"{name}.schema.json").read_text()))


def schema_errors(name: str, data: object) -> list[str]:
    """What the shipped schema ``name`` says of ``data`` (one line per error, with its path)."""
    return [f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator(name).iter_errors(data)]


# --------------------------------------------------------------------------------------- shipped, current
@pytest.mark.parametrize("name", schema_names())
def test_the_shipped_schema_is_the_models_schema(name):
    path = SCHEMA_DIR / f"{name}.schema.json"
    again = f"regenerate it: vslab schema {name} --out configs/schemas/{name}.schema.json"
    assert path.is_file(), f"{path} is missing: {again}"
    assert json.loads(path.read_text(encoding="utf-8")) == schema(name), f"{path} is out of date: {again}"
    assert path.read_text(encoding="utf-8") == schema_text(name), f"{path} is not as written: {again}"


def test_nothing_else_is_shipped_and_the_documented_names_are_known():
    assert {p.name for p in SCHEMA_DIR.glob("*.json")} == {f"{n}.schema.json" for n in schema_names()}
    assert set(SCHEMAS) == {"robot", "experiment", "grid"} <= set(schema_names())


@pytest.mark.parametrize("name", schema_names())
def test_each_schema_is_a_valid_json_schema(name):
    jsonschema.Draft202012Validator.check_schema(schema(name))


# ------------------------------------------------------------------------------------ the configs' files
def schema_of(path: Path) -> str:
    """The schema a file of configs/ should name: by its folder (and an experiment by its file's name)."""
    folder = path.parent.name
    return {"robots": "robot", "train": "grid"}.get(folder) or f"experiment-{path.stem}"


@pytest.mark.parametrize("path", YAMLS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_config_names_its_schema_and_validates(path):
    first = path.read_text(encoding="utf-8").splitlines()[0]
    header = HEADER.fullmatch(first)
    assert header, f"{path}: first line {first!r} does not name its schema"
    assert header.group(1) == f"../schemas/{schema_of(path)}.schema.json"
    assert (path.parent / header.group(1)).is_file()
    assert schema_errors(schema_of(path), yaml.safe_load(path.read_text(encoding="utf-8"))) == []


@pytest.mark.parametrize("path", sorted(EXPERIMENT_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_the_any_experiment_schema_takes_every_experiment_file(path):
    assert schema_errors("experiment", yaml.safe_load(path.read_text(encoding="utf-8"))) == []


def test_the_loaders_still_read_the_files_with_their_header():
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        load_robot(path)
    for path in sorted(EXPERIMENT_DIR.glob("*.yaml")):
        check_experiment(path.stem, load_experiment(path), path.name)
    from pipeline.grid import load_grid

    for path in sorted((CONFIGS / "train").glob("*.yaml")):
        load_grid(path)


# ----------------------------------------------------------------------- a wrong field: both refuse it
def edit(path: Path, change: Callable[[dict], object]) -> dict:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    change(data)
    return data


def setting(*keys_and_value):
    """A change that sets ``data[k1][k2]… = value``."""
    *keys, value = keys_and_value

    def change(data):
        for key in keys[:-1]:
            data = data[key]
        data[keys[-1]] = value

    return change


def renaming(*keys_old_new):
    """A change that renames a key of ``data[k1][k2]…`` (a misspelt key)."""
    *keys, old, new = keys_old_new

    def change(data):
        for key in keys:
            data = data[key]
        data[new] = data.pop(old)

    return change


def dropping(key):
    return lambda data: data.pop(key)


ROBOT_CASES = {  # (file, change): an unknown key, a wrong type, a value out of its set, a misspelt nested key
    "unknown key": ("vsl", setting("colour", "red")),
    "wrong type": ("vsl", setting("kinematics", "l1_m", "long")),
    "out of its set": ("popup", lambda d: d["joints"][0].update(drive="hydraulic")),
    "misspelt nested key": ("vsl", renaming("pneumatics", "channels", "chanels")),
    "misspelt key in a list item": ("popup", renaming("masses", 0, "mass_kg", "mass_g")),
    "missing key": ("vsl", dropping("pneumatics")),
    "extends, unknown key": ("vsl_unmodelled", setting("colour", "red")),
    "extends, misspelt nested key": ("vsl_unmodelled", renaming("effects", "creep", "fractions", "fraction")),
    "extends, wrong type": ("vsl_unmodelled", setting("effects", "elongation", "strain_per_bar", "high")),
    "extends, not a name": ("vsl_unmodelled", setting("extends", 3)),
}


@pytest.mark.parametrize("case", ROBOT_CASES)
def test_a_wrong_robot_field_is_refused_by_the_schema_and_by_vslab(tmp_path, case):
    robot, change = ROBOT_CASES[case]
    data = edit(CONFIG_DIR / f"{robot}.yaml", change)
    assert schema_errors("robot", data), f"the schema takes {case}"
    path = tmp_path / f"{robot}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(RobotDescriptionError):
        load_robot(path)


def test_a_description_that_extends_another_may_change_one_nested_field(tmp_path):
    data = {"extends": "vsl", "name": "vsl_stiff", "servo": {"p_gain": 900}, "pneumatics": {"channels": 2}}
    assert schema_errors("robot", data) == []
    path = tmp_path / "vsl_stiff.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert load_robot(path).servo.p_gain == 900


EXPERIMENT_CASES = {  # (kind, change)
    "unknown key": ("campaign", setting("speed", 3)),
    "wrong type": ("experiment1", setting("repetitions", "five")),
    "not true or false": ("experiment1", setting("rigid_arm", "yes")),
    "out of its set": ("campaign", setting("visit_order", "sorted")),
    "negative count": ("popup_static", setting("load_steps", -6)),
    "out of its range": ("popup_reach", setting("payload_kg", 50.0)),
    "not positive": ("popup_reach", setting("v0_m_s", 0.0)),
    "a list too short": ("popup_deploy", setting("pose_deg", [0.0, 90.0])),
    "an empty list": ("popup_impact", setting("pressures_kpa", [])),
    "a wait too long": ("popup_survey", setting("settle_s", 1e9)),
    "misspelt nested key": ("campaign", renaming("workspace_mm", "max", "maxi")),
    "misspelt key of a case": ("experiment2", renaming("cases", 0, "payload_g", "payload_gram")),
    "missing key": ("popup_deploy", dropping("hold_s")),
    "unknown command mode": ("experiment2", setting("commands", ["ik", "magic"])),
}  # fmt: skip


def vslab_checks_experiment(path: Path) -> None:
    """What vslab does with an experiment file before it needs its robots: load, check, and (Experiment 2)
    its command modes."""
    params = load_experiment(path)
    check_experiment(path.stem, params, str(path))
    if path.stem == "experiment2":
        experiment2(None, None, params)  # refuses unknown command modes before it touches a robot


@pytest.mark.parametrize("case", EXPERIMENT_CASES)
def test_a_wrong_experiment_field_is_refused_by_the_schema_and_by_vslab(tmp_path, case):
    kind, change = EXPERIMENT_CASES[case]
    data = edit(EXPERIMENT_DIR / f"{kind}.yaml", change)
    assert schema_errors(f"experiment-{kind}", data), f"the schema takes {case}"
    assert schema_errors("experiment", data), f"the any-experiment schema takes {case}"
    path = tmp_path / f"{kind}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises((ExperimentError, ValueError)):
        vslab_checks_experiment(path)


GRID = CONFIGS / "train" / "lab.yaml"
GRID_CASES = {
    "unknown key": setting("epochs", 3),
    "misspelt training field": renaming("train", "max_epochs", "max_epoch"),
    "wrong type": setting("seeds", ["0"]),
    "a negative seed": setting("seeds", [-1]),
    "out of its range": setting("train", "lr", 0),
    "out of its set (split)": setting("splits", ["split_time"]),
    "out of its set (preset)": lambda d: d["models"][0].update(preset="huge"),
    "out of its set (direction)": lambda d: d["models"][0].update(direction="sideways"),
    "not a tag": lambda d: d["models"][0].update(tag="Forward"),
    "misspelt model field": lambda d: d["models"][0].update(hiden=[8]),
    "a null model field": lambda d: d["models"][0].update(residual=None),
    "not a dataset": setting("datasets", ["camp aign"]),
    "an empty list": setting("models", []),
}


@pytest.mark.parametrize("case", GRID_CASES)
def test_a_wrong_grid_field_is_refused_by_the_schema_and_by_vslab(tmp_path, case):
    from pipeline.grid import GridError, load_grid

    data = edit(GRID, GRID_CASES[case])
    assert schema_errors("grid", data), f"the schema takes {case}"
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(GridError):
        load_grid(path)


# --------------------------------------------------------------- the models against what the loaders use
def test_the_experiment_models_are_the_shipped_files():
    known = {"experiment1", "experiment2", "campaign", *popup_experiments.EXPERIMENTS}
    assert set(EXPERIMENT_FILES) == set(PARAMETERS) == known
    for kind, parameters in PARAMETERS.items():  # every key described; each default is the shipped value
        shipped = yaml.safe_load((EXPERIMENT_DIR / f"{kind}.yaml").read_text(encoding="utf-8"))
        assert set(parameters) == set(shipped), kind
        properties = EXPERIMENT_FILES[kind].model_json_schema()["properties"]
        assert {k: p["default"] for k, p in properties.items()} == shipped, f"{kind}: the model's defaults"


def test_the_grid_model_is_the_loaders_grid():
    from models.hybrid import PRESETS as NETS
    from pipeline.datasets import SPLIT_COLUMNS
    from pipeline.grid import DATASET, GRID_KEYS, NET_KEYS, TRAIN_KEYS
    from pipeline.model_store import TAG
    from pipeline.train import TrainConfig

    assert tuple(GridFile.model_fields) == GRID_KEYS
    assert tuple(TrainFields.model_fields) == TRAIN_KEYS
    defaults = {f.name: f.default for f in dataclasses.fields(TrainConfig)}
    assert {k: f.default for k, f in TrainFields.model_fields.items()} == {k: defaults[k] for k in TRAIN_KEYS}
    assert set(GridModel.model_fields) == {"direction", "preset", "tag", "name", *NET_KEYS}
    assert set(PRESETS) == {key.split("-", 1)[1] for key in NETS} and SPLITS == SPLIT_COLUMNS
    assert TAG_PATTERN == f"^{TAG.pattern}$" and DATASET_PATTERN == f"^{DATASET.pattern}$"


def test_an_experiment_field_says_its_unit_and_default():
    prop = schema("experiment-campaign")["properties"]["move_speed_rad_s"]
    assert prop["default"] == 1.0 and prop["unit"] == "rad/s" and "(rad/s)" in prop["description"]
    assert schema("experiment-campaign")["required"] == list(PARAMETERS["campaign"])


# ------------------------------------------------------------------------------------------ the command
def test_vslab_schema_prints_the_schema_as_json():
    result = runner.invoke(app, ["schema", "robot"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output) == schema("robot")


def test_vslab_schema_writes_a_file(tmp_path):
    out = tmp_path / "grid.schema.json"
    result = runner.invoke(app, ["--quiet", "schema", "grid", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert out.read_text(encoding="utf-8") == schema_text("grid")


def test_vslab_schema_of_an_unknown_name_is_one_line_naming_the_known_ones():
    result = runner.invoke(app, ["schema", "nosuch"])
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), result.output
    assert "'nosuch'" in lines[0] and all(name in lines[0] for name in schema_names())


def test_a_schema_edit_does_not_leak_between_calls():
    first = schema("robot")
    again = copy.deepcopy(first)
    first["$defs"].clear()
    assert schema("robot") == again
