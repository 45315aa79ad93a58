"""The `vslab` command: every command has --help; user errors end in one clear message, no traceback."""

import pytest
from typer.testing import CliRunner

from vslab.cli import app

runner = CliRunner()


@pytest.mark.parametrize(
    "args",
    [[], ["robots"], ["robots", "list"], ["robots", "show"], ["twin"], ["twin", "survey"], ["demo"], ["rig"]],
)
def test_every_command_has_help(args):
    result = runner.invoke(app, [*args, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output


def test_robots_list_shows_the_three_descriptions():
    result = runner.invoke(app, ["robots", "list"])
    assert result.exit_code == 0, result.output
    for name in ("vsl", "vsl_rigid", "popup"):
        assert name in result.output


def test_robots_show_prints_si_json():
    result = runner.invoke(app, ["robots", "show", "vsl"])
    assert result.exit_code == 0, result.output
    assert '"l2_m": 0.25' in result.output


def test_bad_robot_is_one_clear_message(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    result = runner.invoke(app, ["robots", "show", str(bad)])
    assert result.exit_code == 2
    assert "bad.yaml" in result.output and "Field required" in result.output
    assert "Traceback" not in result.output


def test_unknown_robot_lists_known_ones():
    result = runner.invoke(app, ["robots", "show", "scara"])
    assert result.exit_code == 2
    assert "known robots" in result.output


def test_survey_writes_its_grid_to_the_lab(tmp_path):
    result = runner.invoke(
        app, ["--lab", str(tmp_path), "twin", "survey", "--robot", "vsl", "--trajectory", "linear"]
    )
    assert result.exit_code == 0, result.output
    assert (tmp_path / "twin" / "survey_vsl_linear.json").exists()
    assert "0.5 bar" in result.output


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--rig", "--rate", "servo_bus=fast"], "--rate takes DEVICE=HZ"),
        (["--rig", "--rate", "gripper=10"], "has no device 'gripper'"),
        (["--ports", "{missing}"], "no ports file or rig directory"),
        (["--ports", "{broken}"], "not a ports file"),
    ],
)
def test_record_refuses_bad_options_with_one_line(tmp_path, args, says):
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    args = [a.format(missing=tmp_path / "nothing", broken=broken) for a in args]
    result = runner.invoke(app, ["--lab", str(tmp_path / "lab"), "record", *args])
    assert result.exit_code == 2 and says in result.output, result.output
    assert "Traceback" not in result.output


def test_a_recording_where_no_device_answers_fails_and_says_why(tmp_path):
    import json
    import os

    master, slave = os.openpty()  # a serial port nothing answers on (a missing port is refused before)
    try:
        port = os.ttyname(slave)
        ports = tmp_path / "ports.json"
        ports.write_text(json.dumps({"servo_bus": port}))
        args = ["--lab", str(tmp_path / "lab"), "-q", "record", "--ports", str(ports), "--duration", "0.5"]
        result = runner.invoke(app, args)
    finally:
        os.close(master)
        os.close(slave)
    assert result.exit_code == 2, result.output
    assert "servo_bus gave no sample" in result.output and port in result.output
