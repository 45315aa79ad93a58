"""The suite's own machinery: `make check` and `make test` run the tests on a worker per core with
``--dist loadgroup``, and count on a group's tests sharing one worker (the tutorials' quick main job runs once
for every test that reads it: ``tests/conftest.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

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
