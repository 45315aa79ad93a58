"""A robot description's numbers are finite and within a physical range (finding 3 of the issue "Nothing
silently stale, nothing hung, nothing torn"): an infinite or 1e308 link length or joint limit was accepted,
and the command guard, which trusts the joint limits, was switched off by it."""

from __future__ import annotations

from pathlib import Path

import pytest

from models.robot import RobotDescriptionError, load_robot

VSL = Path(__file__).resolve().parents[1] / "configs" / "robots" / "vsl.yaml"


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("l1_m: 0.100", "l1_m: .inf", "l1_m"),
        ("l1_m: 0.100", "l1_m: 1e308", "l1_m"),
        ("upper_rad: 1.5708}", "upper_rad: .inf}", "upper_rad"),
        ("upper_rad: 1.5708}", "upper_rad: 1e308}", "upper_rad"),
        ("lower_rad: -1.5708,", "lower_rad: -.inf,", "lower_rad"),
        ("lower_rad: -1.5708,", "lower_rad: .nan,", "lower_rad"),
    ],
)
def test_a_description_with_an_unphysical_number_is_refused(tmp_path, old, new, field):
    text = VSL.read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "vsl_typo.yaml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    with pytest.raises(RobotDescriptionError) as refused:
        load_robot(path)
    assert str(path) in str(refused.value) and field in str(refused.value), refused.value
