"""Bad configurations and options meet every command with one clear line, before anything starts.

The matrix: robot descriptions (given by path to `robots show`, `record --robot`, and to `simulate` / `run`
through the protocol's `robot`), protocol files and names (`simulate`, `run`), `--set` values (`simulate`,
`run`, `train`), training grids (`train --grid`), ports (`record --ports`, `run --ports`: a ports file naming
/dev/null, a regular file, a path that does not exist, another robot's device; a ports file that is not
one; a folder that is not a rig's), unsafe plans (`run`: refused before the rig, a device or the recorder
starts), and the other options (`--session`, `--duration`, `--benches`, `--seed`, `--workers`, `--lab`,
`vslab figures` on an empty lab, unknown options). Each cell checks: exit status 2, exactly one line that
starts with `error:` and names what is wrong, no "Traceback", the user's files unchanged (hashed before and
after), and nothing made in the lab (no session folder, no rig folder, no model, no figure), no process left.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import psutil
import pytest
from typer.testing import CliRunner

from vslab.cli import app

runner = CliRunner()
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture
def inputs(tmp_path) -> Path:
    """The user's files: broken robot descriptions, protocols, grids and ports files, in one folder."""
    d = tmp_path / "in"
    (d / "p").mkdir(parents=True)
    files = {
        "empty.yaml": "",
        "broken.yaml": "name: vsl\nkinematics: [unclosed\n",
        "list.yaml": "- 1\n- 2\n",
        "wrong.yaml": "name: x\n",
        "date.yaml": "name: 2024-13-01\n",
        # protocols, named after their protocol (the name says which one a file sets)
        "p/campaign.yaml": "robot: vsl\npoints: 3\n",  # parameters missing
        "p/experiment1.yaml": (CONFIGS / "experiments" / "experiment1.yaml").read_text() + "speed: 3\n",
        "p/experiment2.yaml": (CONFIGS / "experiments" / "experiment2.yaml")
        .read_text()
        .replace("repetitions: 5", "repetitions: five"),
        "p/popup_static.yaml": (CONFIGS / "experiments" / "popup_static.yaml")
        .read_text()
        .replace("load_steps: 6", "load_steps: -6"),
        "mine.yaml": (CONFIGS / "experiments" / "campaign.yaml").read_text(),
        # grids
        "g-models.yaml": "models: 3\ndatasets: [campaign]\n",
        "g-preset.yaml": "models:\n  - {direction: forward, preset: huge}\ndatasets: [campaign]\n",
        "g-direction.yaml": "models:\n  - {direction: sideways, preset: paper}\ndatasets: [campaign]\n",
        "g-dataset.yaml": "models:\n  - {direction: forward, preset: paper}\ndatasets: [../../etc]\n",
        "g-unknown.yaml": "models: []\nepochs: 3\n",
        "g-hidden.yaml": "models:\n  - {direction: forward, preset: paper, hidden: [64, -1]}\n",
        "g-train.yaml": "models:\n  - {direction: forward, preset: paper}\ntrain: {lr: fast}\n",
        # ports files
        "null.json": '{"servo_bus": "/dev/null"}',
        "regular.json": '{"servo_bus": "%s"}' % (d / "list.yaml"),
        "missing.json": '{"servo_bus": "%s"}' % (d / "ttyUSB9"),
        "foreign.json": '{"main_board": "/dev/null"}',
        "notports.json": "[1, 2]",
        "brokenports.json": "{not json",
        "emptyports.json": '{"servo_bus": ""}',
    }
    for name, text in files.items():
        (d / name).write_text(text)
    (d / "binary.yaml").write_bytes(np.random.default_rng(1).bytes(500))
    (d / "p" / "campaign.yaml.d").mkdir()
    (d / "folder").mkdir()
    return d


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


def _lines(output: str, prefix: str) -> list[str]:
    return [ln for ln in output.splitlines() if ln.startswith(prefix)]


def _refused(tmp_path: Path, inputs: Path, args: list[str], says: str) -> str:
    """Run ``vslab --lab <tmp>/lab ARGS`` (``{in}`` in an argument: the inputs folder) and check the cell."""
    lab = tmp_path / "lab"
    before = _hashes(inputs)
    children = {p.pid for p in psutil.Process().children(recursive=True)}
    result = runner.invoke(
        app, ["--lab", str(lab), "--quiet", *(a.replace("{in}", str(inputs)) for a in args)]
    )
    out = result.output
    assert "Traceback" not in out, out
    assert result.exception is None or isinstance(result.exception, SystemExit), (result.exception, out)
    assert result.exit_code == 2, out
    errors = _lines(out, "error:")
    assert len(errors) == 1, out
    assert says.replace("{in}", str(inputs)) in errors[0], out
    assert _hashes(inputs) == before, "the user's files changed"
    made = [p for p in lab.rglob("*")] if lab.exists() else []
    assert not made, f"left in the lab: {made}"
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in children and p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE]  # fmt: skip
    assert not left, f"processes left: {[p.cmdline() for p in left]}"
    return errors[0]


# ------------------------------------------------------------------------------------ robot descriptions
ROBOTS = [
    ("empty.yaml", "empty.yaml: expected a mapping of fields at the top level, found nothing"),
    ("broken.yaml", "broken.yaml: line 3: not valid YAML"),
    ("list.yaml", "list.yaml: expected a mapping of fields at the top level, found a list"),
    ("wrong.yaml", "wrong.yaml: description: Field required"),
    ("date.yaml", "date.yaml: not valid YAML (month must be in 1..12)"),
    ("binary.yaml", "binary.yaml: not a text file"),
    ("folder", "folder: cannot be read (Is a directory)"),
    ("nothing.yaml", "nothing.yaml: no such robot description"),
]
ROBOT_COMMANDS = {
    "robots show": ["robots", "show", "{robot}"],
    "record --robot": ["record", "--robot", "{robot}", "--ports", "{in}/null.json"],
    "simulate (protocol's robot)": ["simulate", "campaign", "--set", "robot={robot}", "--set", "points=5"],
    "run (protocol's robot)": ["run", "campaign", "--set", "robot={robot}", "--set", "points=5", "--rig"],
}


@pytest.mark.parametrize("command", list(ROBOT_COMMANDS))
@pytest.mark.parametrize(("robot", "says"), ROBOTS, ids=[r for r, _ in ROBOTS])
def test_a_bad_robot_description(tmp_path, inputs, command, robot, says):
    args = [a.replace("{robot}", str(inputs / robot)) for a in ROBOT_COMMANDS[command]]
    _refused(tmp_path, inputs, args, says)


def test_dev_null_as_a_robot_description(tmp_path, inputs):
    _refused(tmp_path, inputs, ["robots", "show", "/dev/null"], "/dev/null: expected a mapping")


# ------------------------------------------------------------------------------------ protocols
PROTOCOLS = [
    ("nope", "no experiment 'nope' (known: campaign, experiment1"),
    ("{in}/empty.yaml", "empty.yaml: expected a mapping of parameters"),
    ("{in}/broken.yaml", "broken.yaml: line 3: not valid YAML"),
    (
        "{in}/list.yaml",
        "list.yaml: expected a mapping of parameters (like configs/experiments/*.yaml), found a",
    ),
    ("{in}/binary.yaml", "binary.yaml: not a text file"),
    ("{in}/date.yaml", "date.yaml: not valid YAML"),
    ("{in}/nothing.yaml", "no experiment '{in}/nothing.yaml'"),
    ("{in}/folder.yaml", "no experiment '{in}/folder.yaml'"),
    ("{in}/p/campaign.yaml.d", "campaign.yaml.d: a folder, not an experiment file"),
    (
        "{in}/mine.yaml",
        "no plans for experiment '{in}/mine.yaml': an experiment file is named after the experiment",
    ),
    ("{in}/p/campaign.yaml", "p/campaign.yaml: missing parameter(s) ['pressure_bar'"),
    ("{in}/p/experiment1.yaml", "p/experiment1.yaml: unknown parameter(s) ['speed']"),
    ("{in}/p/experiment2.yaml", "p/experiment2.yaml: repetitions: 'five': expected an integer from 1"),
    ("{in}/p/popup_static.yaml", "p/popup_static.yaml: load_steps: -6: expected an integer from 1"),
]


@pytest.mark.parametrize("command", ["simulate", "run"])
@pytest.mark.parametrize(("experiment", "says"), PROTOCOLS, ids=[p.split("/")[-1] for p, _ in PROTOCOLS])
def test_a_bad_experiment(tmp_path, inputs, command, experiment, says):
    args = [command, experiment] + (["--rig"] if command == "run" else [])
    _refused(tmp_path, inputs, args, says)


# ------------------------------------------------------------------------------------ --set
SETS = [
    (["points"], "--set 'points': expected key=value"),
    (["=3"], "--set '=3': '' is not a parameter name"),
    (["po ints=3"], "is not a parameter name"),
    (["points=[1"], "--set points=[1: the value is not YAML"),
    (["points=!!python/object:os.system x"], "the value is not YAML"),
    (["points=!!binary aGk="], "the value must be a number, text, true/false"),
    (["points=3", "points=4"], "--set points is given twice"),
    (["nope=1"], "--set nope: campaign.yaml has no parameter 'nope'"),
    (["points=abc"], "--set points: 'abc': expected an integer from 1"),
    (["points=-5"], "--set points: -5: expected an integer from 1"),
    (["points=2.5"], "--set points: 2.5: expected an integer from 1"),
    (["points=1e12"], "expected an integer from 1 to 1,000,000"),
    (["settle_s=-1"], "--set settle_s: -1: expected a number ≥ 0"),
    (["settle_s=.nan"], "--set settle_s: nan: expected a number ≥ 0"),
    (["move_speed_rad_s=0"], "--set move_speed_rad_s: 0: expected a number > 0"),
    (["payloads_g=[]"], "--set payloads_g: []: expected a non-empty [list]"),
    (["payloads_g=25"], "--set payloads_g: 25: expected a [list]"),
    (["pressure_bar=[0.5]"], "--set pressure_bar: [0.5]: expected 2 values"),
    (["pressure_bar=[2, 0.5]"], "pressure_bar must be [low, high]"),
    (
        ["workspace_mm={min: [0, 0, 0]}"],
        "--set workspace_mm: {'min': [0, 0, 0]}: expected a mapping of min, max",
    ),
    (["robot=nope"], "nope.yaml: no such robot description"),
    (["robot=popup"], "robot 'popup' is not an anthropomorphic arm"),
]


@pytest.mark.parametrize("command", ["simulate", "run"])
@pytest.mark.parametrize(("pairs", "says"), SETS, ids=[" ".join(p)[:30] for p, _ in SETS])
def test_a_bad_set(tmp_path, inputs, command, pairs, says):
    args = [command, "campaign", *(a for p in pairs for a in ("--set", p))]
    _refused(tmp_path, inputs, args + (["--rig"] if command == "run" else []), says)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["experiment1", "--set", "trajectories=[circle]"], "unknown Experiment 1 trajectory 'circle'"),
        (["experiment2", "--set", "commands=[ik, magic]"], "unknown command mode(s) ['magic']"),
        (
            ["experiment2", "--set", "cases=[{payload_g: 25}]"],
            "--set cases: {'payload_g': 25}: expected a mapping",
        ),
        (["popup_static", "--set", "link=link9"], "robot 'popup' has no such link (its links: link2, link1)"),
        (["popup_deploy", "--set", "order=[0, 5]"], "--set order: [0, 5]: a channel of set_points_kpa"),
        (["popup_deploy", "--set", "pose_deg=[0, 90]"], "--set pose_deg: [0, 90]: expected 3 values"),
    ],
)
def test_bad_parameters_of_the_other_protocols(tmp_path, inputs, args, says):
    _refused(tmp_path, inputs, ["simulate", *args], says)


# ------------------------------------------------------------------------------------ grids
GRIDS = [
    ("{in}/empty.yaml", "empty.yaml: empty (a grid names its"),
    ("{in}/broken.yaml", "broken.yaml: line 3: not valid YAML"),
    ("{in}/list.yaml", "list.yaml: expected a mapping of ['models'"),
    ("{in}/binary.yaml", "binary.yaml: not a text file"),
    ("{in}/date.yaml", "date.yaml: not valid YAML"),
    ("{in}/folder", "folder: a folder, not a grid file"),
    ("{in}/nothing.yaml", "no grid file at {in}/nothing.yaml"),
    ("{in}/g-models.yaml", "g-models.yaml: models: expected a non-empty [list], found an integer (3)"),
    ("{in}/g-preset.yaml", "g-preset.yaml: models: model 0: no preset 'huge' for direction 'forward'"),
    ("{in}/g-direction.yaml", "no preset 'paper' for direction 'sideways'"),
    ("{in}/g-dataset.yaml", "g-dataset.yaml: datasets: '../../etc' is not a dataset name"),
    ("{in}/g-unknown.yaml", "g-unknown.yaml: unknown keys ['epochs']"),
    (
        "{in}/g-hidden.yaml",
        "g-hidden.yaml: models: model 0: hidden: [64, -1]: expected a [list] of layer widths",
    ),
    ("{in}/g-train.yaml", "g-train.yaml: train.lr: 'fast': expected a number > 0"),
]


@pytest.mark.parametrize(("grid", "says"), GRIDS, ids=[g.split("/")[-1] for g, _ in GRIDS])
def test_a_bad_grid(tmp_path, inputs, grid, says):
    _refused(tmp_path, inputs, ["train", "--grid", grid], says)


@pytest.mark.parametrize(
    ("pairs", "says"),
    [
        (["max_epochs=abc"], "--set max_epochs: 'abc': expected an integer ≥ 1"),
        (["max_epochs=0"], "--set max_epochs: 0: expected an integer ≥ 1"),
        (["lr=-1"], "--set lr: -1: expected a number > 0"),
        (["train.batch_size=1.5"], "--set train.batch_size: 1.5: expected an integer ≥ 1"),
        (["seeds=3"], "--set seeds: expected a non-empty [list], found an integer (3)"),
        (["seeds=[-1]"], "--set seeds: -1 is not a seed"),
        (["splits=[split_x]"], "--set splits: 'split_x' is not a split"),
        (["nope=1"], "--set nope: not a grid key"),
        (["train={lr: x}"], "--set train: lr: 'x': expected a number > 0"),
        (
            ["models=[{direction: forward}]"],
            "--set models: model 0: needs a direction (forward or inverse) and a",
        ),
        (["max_epochs"], "--set 'max_epochs': expected key=value"),
    ],
    ids=lambda v: str(v)[:30],
)
def test_a_bad_training_set(tmp_path, inputs, pairs, says):
    _refused(tmp_path, inputs, ["train", *(a for p in pairs for a in ("--set", p))], says)


def test_a_grid_without_its_dataset_says_how_to_build_one(tmp_path, inputs):
    _refused(tmp_path, inputs, ["train"], "no dataset 'campaign' under")


# ------------------------------------------------------------------------------------ ports
PORTS = [
    ("{in}/null.json", "null.json: servo_bus: /dev/null: a mem device, not a serial port"),
    ("{in}/regular.json", "regular.json: servo_bus: {in}/list.yaml: a regular file, not a serial port"),
    ("{in}/missing.json", "missing.json: servo_bus: {in}/ttyUSB9: no such port (is the device plugged in?"),
    ("{in}/foreign.json", "foreign.json: main_board: vsl has no such device (its devices: servo_bus"),
    ("{in}/notports.json", "notports.json: expected a JSON object of device name → port path"),
    ("{in}/brokenports.json", "brokenports.json: not a ports file"),
    ("{in}/emptyports.json", "emptyports.json: expected a JSON object of device name → port path"),
    ("{in}/binary.yaml", "binary.yaml: not a ports file"),
    ("{in}/folder", "folder: no ports.json in this folder"),
    ("{in}/nothing", "--ports {in}/nothing: no ports file or rig directory there"),
]


@pytest.mark.slow
@pytest.mark.parametrize("command", ["record", "run"])
@pytest.mark.parametrize(("ports", "says"), PORTS, ids=[p.split("/")[-1] for p, _ in PORTS])
def test_bad_ports(tmp_path, inputs, command, ports, says):
    args = ["record", "--duration", "1"] if command == "record" else ["run", "experiment1", "--plan", "0"]
    _refused(tmp_path, inputs, [*args, "--ports", ports], says)


# ------------------------------------------------------------------------------------ unsafe plans
BELOW = "{min: [250, -80, -150], max: [300, 80, -100]}"  # reachable, below the robot's safety box


@pytest.mark.parametrize("where", [["--rig"], ["--ports", "{in}/null.json"]], ids=["rig", "ports"])
@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["experiment1", "--set", "pressures_bar=[5]"], "channel 0 set to 500000 Pa > 200000 Pa"),
        (["experiment1", "--set", "pressures_bar=[0.1]"], "open at 10000 Pa < 50000 Pa"),
        (["campaign", "--set", "points=5", "--set", f"workspace_mm={BELOW}"], "workspace: tip"),
        (["popup_static", "--set", "allow_wrinkling=false"], "breaks"),
    ],
    ids=["pressure", "low-pressure", "workspace", "wrinkling"],
)
@pytest.mark.slow
def test_an_unsafe_plan_is_refused_before_anything_starts(tmp_path, inputs, where, args, says):
    error = _refused(
        tmp_path, inputs, ["run", *args, "--plan", "0", *where], "safety limit(s): refused, nothing"
    )
    assert "was started" in error
    result = runner.invoke(app, ["--lab", str(tmp_path / "lab"), "-q", "run", *args, "--plan", "0", *where])
    assert says in result.output, result.output  # the limits it breaks follow the error line


# ------------------------------------------------------------------------------------ the other options
@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["record", "--session", "../x", "--rig"], "--session '../x': a session id is a folder name"),
        (["record", "--session", ".hidden", "--rig"], "a session id is a folder name"),
        (["run", "experiment1", "--session", "a/b", "--rig"], "--session 'a/b'"),
        (["record", "--duration", "nan", "--rig"], "--duration must be ≥ 0 s"),
        (["record", "--duration", "-1", "--rig"], "--duration must be ≥ 0 s"),
        (["record", "--rate", "servo_bus=fast", "--rig"], "--rate takes DEVICE=HZ"),
        (["record"], "say where the devices are"),
        (["run", "experiment1", "--plan", "99999", "--rig"], "experiment1 has no plan '99999'"),
        (["run", "experiment2", "--plan", "2", "--rig"], "hybrid commands need a trained inverse model"),
        (
            ["simulate", "experiment2", "--set", "commands=[ik, history]"],
            "history commands need a history-aware",
        ),
        (
            ["run", "experiment2", "--plan", "0", "--set", "commands=[history]", "--rig"],
            "history commands need a history-aware",
        ),
        (["simulate", "campaign", "--benches", "0"], "--benches must be ≥ 1"),
        (["simulate", "campaign", "--seed", "-1"], "--seed ≥ 0"),
        (["simulate", "campaign", "--processes", "0"], "--processes must be ≥ 1"),
        (["simulate", "campaign", "--benches", "many"], "Invalid value for '--benches'"),
        (["simulate", "campaign", "--nope"], "No such option: --nope"),
        (["simulate"], "Missing argument 'experiment'"),
        (["train", "--workers", "-1"], "--workers must be ≥ 0"),
        (["demo", "--seed", "-1"], "--seed must be ≥ 0"),
        (["demo", "--seed", "x"], "Invalid value for '--seed'"),
        (["figures"], "no datasets in"),
        (["models", "show", "abc"], "no model version 'abc'"),
    ],
    ids=lambda v: " ".join(v)[:40] if isinstance(v, list) else None,
)
def test_bad_options(tmp_path, inputs, args, says):
    _refused(tmp_path, inputs, args, says)


def test_a_lab_that_is_a_file(tmp_path, inputs):
    lab = inputs / "list.yaml"
    before = _hashes(inputs)
    result = runner.invoke(app, ["--lab", str(lab), "simulate", "campaign"])
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    (error,) = _lines(result.output, "error:")
    assert f"--lab {lab}: not a directory" in error
    assert _hashes(inputs) == before
