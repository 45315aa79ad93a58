"""The `--set key=value` parser (`vslab.app.parse_set`), property-tested.

Any list of strings either parses into {name: plain value} or raises the documented `SetError` (a
ValueError naming the pair), never anything else; valid values round-trip (JSON text, and numbers and
booleans as a user types them); and through the CLI any `--set` ends in at most one `error:` line, never a
traceback.
"""

from __future__ import annotations

import json
import math
import re

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from vslab.app import SetError, parse_set
from vslab.cli import app

SETTINGS = settings(derandomize=True, deadline=None, max_examples=300)
KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")

names = st.from_regex(KEY, fullmatch=True).filter(lambda k: len(k) < 40)
text = st.text(st.characters(max_codepoint=0xFFFF, exclude_categories=("Cs",)), max_size=20)
scalars = st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False) | text


def _containers(inner):
    return st.lists(inner, max_size=4) | st.dictionaries(text, inner, max_size=4)


values = st.recursive(scalars, _containers, max_leaves=12)


def _plain(value) -> bool:
    if value is None or isinstance(value, bool | int | str):
        return True
    if isinstance(value, float):
        return True  # nan and inf are plain YAML (.nan, .inf); the protocols and grids refuse them
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    return isinstance(value, dict) and all(isinstance(k, str) and _plain(v) for k, v in value.items())


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


@pytest.mark.slow
@SETTINGS
@given(st.lists(st.text(max_size=40), max_size=4))
@example(["points"])
@example(["=1"])
@example(["a=1", "a=2"])
@example(["a=[1"])
@example(["a=2024-13-01"])
@example(["a=!!python/object/apply:os.system [ls]"])
@example(["a=!!binary aGk="])
@example(["a=" + "9" * 5000])
@example(["a=" + "[" * 2000])
@example(["a=\x00"])
@example(["a=*x"])
def test_any_strings_parse_or_raise_the_documented_error(pairs):
    try:
        parsed = parse_set(pairs)
    except SetError as exc:
        assert isinstance(exc, ValueError)
        assert str(exc).startswith("--set ") and "\n" not in str(exc)
        return
    assert len(parsed) == len(pairs)
    assert all(KEY.fullmatch(k) for k in parsed)
    assert all(_plain(v) for v in parsed.values())


@pytest.mark.slow
@SETTINGS
@given(names, values)
def test_json_values_round_trip(key, value):
    assert _same(parse_set([f"{key}={json.dumps(value)}"]), {key: value})


@pytest.mark.slow
@SETTINGS
@given(names, st.integers() | st.floats(allow_nan=False, allow_infinity=False) | st.booleans())
def test_numbers_and_booleans_as_typed_round_trip(key, value):
    typed = str(value).lower() if isinstance(value, bool) else repr(value)  # 1e-05, 0.1, 12, true
    assert _same(parse_set([f" {key} = {typed} "]), {key: value})


def test_what_users_type():
    typed = ["points=2000", "lr=1e-4", "commands=[ik,static]", "rigid_arm=false", "train.lr=.5"]
    expected = {"points": 2000, "lr": 1e-4, "commands": ["ik", "static"], "rigid_arm": False, "train.lr": 0.5}
    assert parse_set(typed) == expected
    assert parse_set(["cases=[{payload_g: 25, pressure_bar: 1.5}]"]) == {
        "cases": [{"payload_g": 25, "pressure_bar": 1.5}]
    }
    assert parse_set(["when=2024-01-02", "name='a b'", "empty="]) == {
        "when": "2024-01-02", "name": "a b", "empty": None}  # fmt: skip


@settings(derandomize=True, deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(max_size=30))
@example("max_epochs=[")
@example("seeds=!!set {1}")
def test_through_the_cli_any_set_is_one_error_line_at_most(tmp_path_factory, pair):
    """`vslab train --set PAIR` in an empty lab: whatever PAIR is, one `error:` line (a bad pair, a bad value
    for its key, or no dataset to train on), exit 2, no traceback."""
    lab = tmp_path_factory.mktemp("lab")
    result = CliRunner().invoke(app, ["--lab", str(lab), "--quiet", "train", "--set", pair])
    assert "Traceback" not in result.output, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), (result.exception, pair)
    assert result.exit_code == 2, result.output
    assert len([ln for ln in result.output.splitlines() if ln.startswith("error:")]) == 1, result.output
    assert not any(lab.iterdir())
