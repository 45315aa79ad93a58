"""Every experiment's ``--set`` keys fed random values (numbers with ±inf, nan, 1e±308 and huge integers,
text, lists): ``vslab simulate --dry-run`` ends in a plan or in one ``error:`` line with exit 2, within 30 s,
and leaves no process behind (finding 3 of the issue "Nothing silently stale, nothing hung, nothing torn")."""

from __future__ import annotations

import json
import time

import psutil
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from acquisition.plans.experiments import EXPERIMENT_DIR
from vslab.cli import app

EXPERIMENTS = sorted(p.stem for p in EXPERIMENT_DIR.glob("*.yaml"))
KEYS = [(e, k) for e in EXPERIMENTS for k in yaml.safe_load((EXPERIMENT_DIR / f"{e}.yaml").read_text())]
# kept small where the key is not the one drawn: a valid draw then builds in a second, not a campaign's 17,568
SMALL = {"campaign": {"points": 3}, "popup_survey": {"points": 3}, "experiment1": {"repetitions": 1}}
EDGES = ["1e308", "-1e308", "1e-308", "1e-300", ".inf", "-.inf", ".nan", "0", "-1", str(10**30), "true"]

numbers = (
    st.integers(1, 4).map(str)  # in range for most keys: some draws build a plan
    | st.floats(0.01, 1.0).map(lambda x: f"{x:.3g}")
    | st.sampled_from(EDGES)
    | st.integers(-(10**20), 10**20).map(str)
    | st.floats(allow_nan=True, allow_infinity=True).map(lambda x: yaml.safe_dump(x).splitlines()[0])
)
texts = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=8).map(json.dumps)
values = numbers | texts | st.lists(numbers | texts, max_size=4).map(lambda v: "[" + ", ".join(v) + "]")


@pytest.mark.slow
@settings(derandomize=True, deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(KEYS), values)
def test_any_set_value_ends_in_a_plan_or_one_error_line(tmp_path_factory, key, value):
    experiment, name = key
    small = {k: v for k, v in SMALL.get(experiment, {}).items() if k != name}
    args = [f"{k}={v}" for k, v in small.items()] + [f"{name}={value}"]
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    start = time.monotonic()
    lab = tmp_path_factory.mktemp("lab")
    result = CliRunner().invoke(app, ["--lab", str(lab), "simulate", experiment, "--dry-run",
                                      *(a for pair in args for a in ("--set", pair))])  # fmt: skip
    elapsed = time.monotonic() - start
    out = result.output
    assert elapsed < 30, (args, elapsed)
    assert "Traceback" not in out, out
    assert result.exception is None or isinstance(result.exception, SystemExit), (args, result.exception)
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    if result.exit_code == 0:
        assert not errors and "dry run: nothing simulated" in out, out
    else:
        assert result.exit_code == 2 and len(errors) == 1, (args, out)
    left = {p.pid for p in psutil.Process().children(recursive=True)} - before
    assert not left, f"{args}: processes left behind: {left}"
