"""A plain `pip install .` (no extras) runs the lab: a fresh virtual environment simulates a small campaign,
builds its dataset and trains a network. Nothing a command needs may hide in the `[dev]` extra
(mcap-ros2-support is only the tests' reference CDR decoder), and the configs/ the code reads ship with it.
Measured here (2 cores, pip taking torch's wheel and the rest from this machine's local package index):
≈ 55 s for the environment and the install, ≈ 65 s in all with the three commands.

The source goes in as a fresh clone would have it (the files git tracks, and new ones it does not ignore),
copied to a temporary folder, so the build leaves nothing in the working tree. Skipped, with the reason,
where pip cannot reach a package index (it needs one for the build backend and the dependencies).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GRID = """\
models:
  - {direction: forward, preset: small-residual}
datasets: [campaign]
splits: [split_random]
seeds: [0]
train: {max_epochs: 3, patience: 2, batch_size: 64}
"""


def _source(dest: Path) -> Path:
    """The project's files as a clone has them (tracked, or new and not ignored), copied to ``dest``."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    for name in filter(None, listed):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


def _run(*args, timeout: float, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, **kwargs)


@pytest.mark.slow
def test_a_plain_install_runs_simulate_build_and_train(tmp_path):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs the project's git checkout (to install what a clone holds)")
    start = time.perf_counter()
    venv = tmp_path / "venv"
    _run(sys.executable, "-m", "venv", venv, timeout=300, check=True)
    python, vslab = venv / "bin" / "python", venv / "bin" / "vslab"
    probe = _run(python, "-m", "pip", "download", "--no-deps", "--dest", tmp_path / "probe", "setuptools>=77",
                 timeout=600)  # fmt: skip
    if probe.returncode != 0:
        why = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.skip(f"no package index reachable (pip could not fetch setuptools: {why})")
    source = _source(tmp_path / "src")
    install = _run(python, "-m", "pip", "install", "--quiet", source, timeout=1800)
    assert install.returncode == 0, install.stdout[-2000:] + install.stderr[-4000:]
    installed_s = time.perf_counter() - start
    for dev_only in ("mcap_ros2", "distributed", "s3fs", "mlflow", "yourdfpy"):  # dev tools; the rest: extras
        absent = _run(python, "-c", f"import {dev_only}", timeout=60)
        assert absent.returncode != 0, f"{dev_only} came with a plain install: not a test of one"

    lab = tmp_path / "lab"
    grid = tmp_path / "grid.yaml"
    grid.write_text(GRID)
    env = {**os.environ, "VSLAB_BATCH_NICE": "0"}
    steps = [
        ["simulate", "campaign", "--benches", "2", "--set", "points=60"],
        ["build", "--name", "campaign"],
        ["train", "--grid", grid, "--workers", "1"],
    ]
    for step in steps:
        done = _run(vslab, "--lab", lab, "--quiet", *step, timeout=900, cwd=tmp_path, env=env)
        assert done.returncode == 0, f"vslab {step[0]}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        assert "Traceback" not in done.stdout + done.stderr, done.stderr[-3000:]
    for extra in (["build", "--name", "campaign", "--cluster", "tcp://127.0.0.1:9"], ["cluster", "local"]):
        done = _run(vslab, "--lab", lab, "--quiet", *extra, timeout=300, cwd=tmp_path, env=env)
        assert done.returncode == 2 and "pip install 'vslab[cluster]'" in done.stdout, (
            done.stdout + done.stderr
        )
        assert "Traceback" not in done.stdout + done.stderr
    done = _run(vslab, "--lab", "s3://bucket/lab", "sessions", "list", timeout=300, cwd=tmp_path, env=env)
    assert done.returncode == 2 and "pip install 'vslab[s3]'" in done.stdout, done.stdout + done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    done = _run(vslab, "--lab", lab, "models", "export-mlflow", timeout=300, cwd=tmp_path, env=env)
    assert done.returncode == 2 and "pip install 'vslab[mlflow]'" in done.stdout, done.stdout + done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    session = sorted(p.name for p in (lab / "sessions").iterdir())[0]
    done = _run(vslab, "--lab", lab, "--quiet", "sessions", "export", session, "--foxglove", timeout=300,
                cwd=tmp_path, env=env)  # fmt: skip
    assert done.returncode == 0 and (lab / "exports" / f"{session}.foxglove.mcap").is_file(), done.stdout
    assert list((lab / "datasets" / "campaign").glob("*/data.parquet"))
    assert list((lab / "models").glob("*/*/weights.safetensors"))
    print(f"plain install: venv + pip install {installed_s:.0f} s; "
          f"with simulate, build, train {time.perf_counter() - start:.0f} s")  # fmt: skip
