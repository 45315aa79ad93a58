"""Robot descriptions: the shipped files load, and bad files give one message naming file, field, reason."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from models.robot import CONFIG_DIR, RobotDescriptionError, load_robot


@pytest.mark.parametrize("name", ["vsl", "vsl_rigid", "popup", "vsl_unmodelled"])
def test_shipped_descriptions_load(name):
    robot = load_robot(name)
    assert robot.name == name
    assert robot.actuated_joints == ["q1", "q2", "q3"]
    assert robot.joint_limits().shape == (3, 2)


def test_vsl_chain_places_virtual_joints_at_the_prbm_hinge():
    robot = load_robot("vsl")
    rows = {r.joint: r for r in robot.dh_rows()}
    assert [r.joint for r in robot.dh_rows()] == ["q1", "q2", "d2", "q3", "d3"]
    assert rows["q2"].a_m + rows["d2"].a_m == pytest.approx(robot.kinematics.l2_m)
    assert rows["q2"].a_m == pytest.approx(0.15 * robot.kinematics.l2_m)


def test_popup_link1_table_is_link2_scaled_by_second_moment_ratio():
    robot = load_robot("popup")
    k1 = robot.link_table("link1").stiffness_nm_per_rad
    k2 = robot.link_table("link2").stiffness_nm_per_rad
    assert [a / b for a, b in zip(k1, k2, strict=True)] == pytest.approx([(85 / 55) ** 3] * len(k2), rel=1e-3)
    assert robot.virtual_joints == ["d11", "d12", "d21", "d22"]


def test_popup_mass_is_under_four_kilograms():
    robot = load_robot("popup")
    base_motor = 0.8  # J1's motor sits on the base and is not in the chain
    assert sum(m.mass_kg for m in robot.masses) + base_motor < 4.0


def _write_variant(tmp_path: Path, edit) -> Path:
    data = yaml.safe_load((CONFIG_DIR / "vsl.yaml").read_text())
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _set(path: list, value):
    def edit(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return edit


def _delete(path: list):
    def edit(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]

    return edit


BAD_FILES = [
    # (edit, field named in the message, words of the reason)
    (_set(["masses", 0, "mass_kg"], -0.1), "masses.0.mass_kg", "greater than or equal to 0"),
    (_set(["kinematics", "l2_m"], "long"), "kinematics.l2_m", "valid number"),
    (
        _delete(["pneumatics", "regulator_time_constant_s"]),
        "pneumatics.regulator_time_constant_s",
        "Field required",
    ),
    (_set(["servo", "p_gian"], 800), "servo.p_gian", "Extra inputs are not permitted"),
    (
        _set(["links", 0, "table", "pressure_pa"], [50000, 10000, 100000, 150000, 200000, 250000]),
        "links.0.table",
        "strictly increasing",
    ),
    (
        _set(["links", 0, "table", "stiffness_nm_per_rad"], [8.0, 40.0]),
        "links.0.table",
        "stiffness_nm_per_rad has 2",
    ),
    (_set(["masses", 1, "frame"], "elbow"), "(top level)", "frame 'elbow' is not one of"),
    (_set(["joints", 0, "lower_rad"], 2.0), "joints.0", "must be below upper_rad"),
    (_set(["kinematics", "type"], "scara"), "kinematics", "does not match any of the expected tags"),
    (_set(["sensors", "tracker", "field_min_m"], [0.3, -0.25, 0.05]), "sensors.tracker", "field_min_m"),
    (_set(["pneumatics", "max_operating_pa"], 400000), "pneumatics", "exceeds regulator_max_pa"),
]


@pytest.mark.parametrize(("edit", "field", "reason"), BAD_FILES)
def test_bad_description_names_file_field_and_reason(tmp_path, edit, field, reason):
    path = _write_variant(tmp_path, edit)
    with pytest.raises(RobotDescriptionError) as info:
        load_robot(path)
    message = str(info.value)
    assert str(path) in message
    assert f": {field}:" in message
    assert reason in message
    assert "Traceback" not in message


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("name: vsl\nkinematics: [unclosed\n")
    with pytest.raises(RobotDescriptionError, match=r"broken\.yaml: line \d+: not valid YAML"):
        load_robot(path)


def test_missing_file_lists_known_robots(tmp_path):
    with pytest.raises(RobotDescriptionError, match=r"no such robot description .*'popup'"):
        load_robot("no_such_robot")


def test_top_level_must_be_a_mapping(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(RobotDescriptionError, match="expected a mapping"):
        load_robot(path)


def test_every_assumed_value_is_commented():
    """Each robot file marks provenance: a numeric line without a comment must sit in a commented block."""
    for path in CONFIG_DIR.glob("*.yaml"):
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            body = line.split("#")[0]
            if not any(ch.isdigit() for ch in body.split(":", 1)[-1]) or "#" in line:
                continue
            # walk up to the enclosing block: some line above at lower-or-equal indent must carry a comment
            indent = len(line) - len(line.lstrip())
            above = [ln for ln in lines[max(0, i - 6) : i] if "#" in ln]
            assert above, (
                f"{path.name}:{i + 1}: value without a provenance comment: {line.strip()} ({indent})"
            )


def test_the_statics_cross_product_is_numpys_bit_for_bit():
    """The gravity moments' written-out cross product (``models.statics._cross``) gives np.cross's values
    exactly, over the shapes the statics pass it (masses × batch, and one vector per batch row)."""
    from models.statics import _cross

    rng = np.random.default_rng(7)
    for shape_a, shape_b in [((7, 5, 3), (5, 3)), ((7, 3), (7, 3)), ((3,), (3,)), ((2, 4, 5, 3), (5, 3))]:
        a, b = rng.normal(size=shape_a) * 10, rng.normal(size=shape_b)
        assert np.array_equal(_cross(a, b), np.cross(a, b)), (shape_a, shape_b)


def test_the_d_h_rows_are_the_validated_rows():
    """The rows a description builds without validating them again equal rows validated from the same
    numbers (and dump the same)."""
    from models.robot import DHRowSpec

    for name in ("vsl", "vsl_unmodelled", "vsl_rigid"):
        for row in load_robot(name).dh_rows():
            checked = DHRowSpec.model_validate(row.model_dump())
            assert checked == row and checked.model_dump() == row.model_dump()
