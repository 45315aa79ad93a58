"""Builds and grids on a real Dask cluster (``LocalCluster``: 2 worker processes on 127.0.0.1, started and
stopped here): the same dataset versions and bit-identical weights as on one machine, a worker killed
mid-job retried, and one clear error where no scheduler answers."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pandas as pd
import pytest
import yaml
from conftest import absent_service_ports
from distributed import Client
from safetensors.torch import load_file
from typer.testing import CliRunner

from pipeline.build import build
from pipeline.cluster import ClusterError, cluster_executor, local_cluster
from pipeline.grid import load_grid, run_grid
from pipeline.lab import Lab
from vslab.cli import app

GRID = {
    "models": [{"direction": "forward", "preset": "small-residual", "hidden": [16, 16]},
               {"direction": "inverse", "preset": "paper", "hidden": [16, 16]}],
    "datasets": ["campaign"], "splits": ["split_random"], "seeds": [0, 1],
    "train": {"max_epochs": 4, "patience": 4, "batch_size": 64},
}  # fmt: skip


@pytest.fixture(scope="module")
def cluster():
    with local_cluster(2, port=0) as started:
        yield started.scheduler_address


def _lab(tmp_path, campaign_dataset, name: str):
    """A fresh lab reading the campaign's sessions (and, for training, its dataset)."""
    src, _, _ = campaign_dataset
    lab = tmp_path / name
    lab.mkdir()
    (lab / "sessions").symlink_to(src / "sessions")
    return lab


@pytest.mark.slow
def test_a_build_on_the_cluster_is_the_local_build(tmp_path, campaign_dataset, cluster):
    src, version, _ = campaign_dataset
    lab = _lab(tmp_path, campaign_dataset, "remote")
    sessions = sorted((lab / "sessions").iterdir())
    with cluster_executor(cluster) as executor:
        report = build(sessions, Lab(lab), "campaign", executor=executor)
    assert report.built and report.cached == 0 and report.version == version
    for table in ("data", "trajectories"):
        local = src / "datasets" / "campaign" / version / f"{table}.parquet"
        if local.exists():
            pd.testing.assert_frame_equal(
                pd.read_parquet(report.path / f"{table}.parquet"), pd.read_parquet(local)
            )


def _weights(lab, results) -> dict[str, dict]:
    return {
        r["version"]: load_file(lab / "models" / r["name"] / r["version"] / "weights.safetensors")
        for r in results
    }


@pytest.mark.slow
def test_a_grid_on_the_cluster_trains_the_local_weights_even_when_a_worker_dies(
    tmp_path, campaign_dataset, cluster
):
    src, _, _ = campaign_dataset
    grid_file = tmp_path / "grid.yaml"
    grid_file.write_text(yaml.safe_dump(GRID))
    local_lab, remote_lab = (_lab(tmp_path, campaign_dataset, name) for name in ("local", "remote"))
    for lab in (local_lab, remote_lab):
        (lab / "datasets").symlink_to(src / "datasets")
    local = run_grid(Lab(local_lab), load_grid(grid_file), workers=1, threads=1)
    with Client(cluster, set_as_default=False) as client, cluster_executor(cluster) as executor:
        victim = next(iter(client.run(os.getpid).values()))  # one worker's process
        killer = threading.Timer(1.5, os.kill, (victim, signal.SIGKILL))  # mid-job: a job takes seconds
        killer.start()
        started = time.monotonic()
        remote = run_grid(Lab(remote_lab), load_grid(grid_file), executor=executor, threads=1)
        killer.join()
        assert time.monotonic() - started > 1.5, "the worker died while the grid ran"
        assert victim not in client.run(os.getpid).values()  # its nanny started a new one
    assert [r["version"] for r in remote] == [r["version"] for r in local]
    assert {r["status"] for r in remote} == {"trained"}
    a, b = _weights(local_lab, local), _weights(remote_lab, remote)
    for version, tensors in a.items():
        assert tensors.keys() == b[version].keys()
        assert all(tensors[k].equal(b[version][k]) for k in tensors), f"{version}: weights differ"


@pytest.mark.slow
def test_no_scheduler_is_one_clear_error(tmp_path, campaign_dataset):
    with pytest.raises(ClusterError, match=r"no Dask scheduler answers at 'tcp://127.0.0.1:9' within 1 s"):
        with cluster_executor("tcp://127.0.0.1:9", timeout_s=1):
            pass
    src, _, _ = campaign_dataset
    lab = _lab(tmp_path, campaign_dataset, "lab")
    (lab / "datasets").symlink_to(src / "datasets")
    (tmp_path / "grid.yaml").write_text(yaml.safe_dump(GRID))
    nowhere = ["--cluster", "tcp://127.0.0.1:9"]
    for command in (
        ["build", "--name", "other", "--experiment", "campaign"],
        ["train", "--grid", str(tmp_path / "grid.yaml")],
    ):
        done = CliRunner().invoke(app, ["--lab", str(lab), *command, *nowhere])
        assert done.exit_code == 2, done.output
        assert "error: no Dask scheduler answers at 'tcp://127.0.0.1:9'" in done.output
        assert "Traceback" not in done.output
    done = CliRunner().invoke(app, ["--lab", str(lab), "build", "--workers", "2", *nowhere])
    assert done.exit_code == 2 and "--workers and --cluster" in done.output


@pytest.mark.slow
def test_vslab_cluster_local_serves_until_ctrl_c():
    command = [
        sys.executable,
        "-m",
        "vslab.cli",
        "--quiet",
        "cluster",
        "local",
        "--workers",
        "1",
        "--port",
        "0",
    ]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    try:
        line = proc.stdout.readline()
        address = re.search(r"--cluster (tcp://\S+);", line).group(1)
        with cluster_executor(address) as executor:
            assert executor.submit(pow, 2, 10).result(timeout=30) == 1024
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
        assert "cluster stopped" in proc.stdout.read() and "Traceback" not in proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.slow
def test_a_scheduler_that_is_not_there_is_one_line_within_seconds(tmp_path, campaign_dataset):
    """Nothing on the port (bound and closed), and a port that accepts but never speaks: each one `error:`
    line naming the address, well within a minute (old code: the second hung for ever in Dask's handshake)."""
    lab = _lab(tmp_path, campaign_dataset, "lab")
    with absent_service_ports() as ports:
        for port in ports:
            address = f"tcp://127.0.0.1:{port}"
            command = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), "build", "--cluster", address]
            start = time.monotonic()
            done = subprocess.run(command, capture_output=True, text=True, timeout=120)
            elapsed = time.monotonic() - start
            said = (done.stdout + done.stderr).strip().splitlines()
            assert done.returncode == 2 and len(said) == 1, said
            assert said[0].startswith(f"error: no Dask scheduler answers at '{address}' within 5 s"), said
            assert elapsed < 30, f"{address}: {elapsed:.1f} s to say no scheduler is there"
