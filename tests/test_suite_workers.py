"""The suite's own machinery: `make check` and `make test` run the tests on a worker per core with
``--dist loadgroup``, and count on a group's tests sharing one worker (the tutorials' quick main job runs once
for every test that reads it: ``tests/conftest.py``)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

GROUPED = """
import os
import pytest

@pytest.mark.xdist_group("together")
@pytest.mark.parametrize("i", range(4))
def test_grouped(i):
    with open(os.path.join({out!r}, f"{name}-{{i}}"), "w") as f:
        f.write(os.environ["PYTEST_XDIST_WORKER"])
"""


def test_a_group_of_tests_runs_on_one_worker(tmp_path):
    """Fails on pytest 9.2 with pytest-xdist 3.8 (pytest-xdist issue 1386: the groups are silently lost),
    hence pytest < 9.2 in the dev extra."""
    out = tmp_path / "workers"
    out.mkdir()
    for name in ("a", "b"):
        (tmp_path / f"test_{name}.py").write_text(textwrap.dedent(GROUPED.format(name=name, out=str(out))))
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadgroup", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), "-c", "/dev/null", str(tmp_path)],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
        env={k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")},
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    workers = {p.name: p.read_text() for p in out.iterdir()}
    assert len(workers) == 8, workers
    assert len(set(workers.values())) == 1, f"the group ran on several workers: {workers}"


def test_the_real_time_run_finds_every_real_time_test_by_its_file():
    """The Makefile's real-time run collects only the files that name the ``real_time`` fixture (a test asks
    for it by name; ``tests/conftest.py`` marks that test real_time). A fixture shared from a conftest that
    asked for it would mark tests in files that never name it: the workers' run would deselect them and the
    real-time run would not collect them, so they would silently never run."""
    tests = Path(__file__).resolve().parent
    for conftest in tests.rglob("conftest.py"):
        for node in ast.walk(ast.parse(conftest.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                arguments = [a.arg for a in node.args.args + node.args.kwonlyargs]
                assert "real_time" not in arguments, (
                    f"{conftest}:{node.lineno}: {node.name} asks for real_time on its tests' behalf; "
                    "the Makefile's REAL_TIME_FILES would miss them (ask for it in the test file)"
                )
    makefile = (tests.parent / "Makefile").read_text()
    assert "REAL_TIME_FILES = $(shell grep -lw real_time tests/test_*.py)" in makefile
    named = {p.name for p in tests.glob("test_*.py") if re.search(r"\breal_time\b", p.read_text())}
    assert {
        "test_recorder.py",
        "test_rig.py",
        "test_can_drives.py",
    } <= named  # the real-time tests' own files
