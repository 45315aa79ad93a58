"""``vslab models export-mlflow``: a lab's model versions as MLflow runs in a local SQLite store, read back
through the MLflow client; exporting twice duplicates nothing."""

from __future__ import annotations

import contextlib
import http.server
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time

import mlflow
import numpy as np
import pytest
import yaml

from pipeline import model_store
from pipeline.grid import load_grid, run_grid
from pipeline.lab import Lab
from pipeline.mlflow_export import NAME_TAG, VERSION_TAG, MlflowExportError, _reachable, run_metrics


@pytest.fixture(scope="module")
def lab(tmp_path_factory, campaign_dataset):
    """A lab with two tiny model versions trained on the session's campaign dataset."""
    src, _, _ = campaign_dataset
    lab = tmp_path_factory.mktemp("mlflow-lab")
    (lab / "datasets").symlink_to(src / "datasets")
    grid = {
        "models": [{"direction": "forward", "preset": "small-residual", "hidden": [16, 16]},
                   {"direction": "inverse", "preset": "paper", "hidden": [16, 16]}],
        "datasets": ["campaign"], "splits": ["split_random"], "seeds": [0],
        "train": {"max_epochs": 3, "patience": 3, "batch_size": 128},
    }  # fmt: skip
    path = lab / "grid.yaml"
    path.write_text(yaml.safe_dump(grid))
    run_grid(Lab(lab), load_grid(path), workers=1, threads=1)
    return lab


def _cli(lab, *args, env=None):
    command = [sys.executable, "-m", "vslab.cli", "--lab", str(lab), *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)


@pytest.mark.slow
def test_every_model_version_becomes_one_run_and_exporting_again_adds_none(lab, tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    done = _cli(lab, "models", "export-mlflow", "--tracking-uri", uri)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "2 run(s) logged, 0 already there" in done.stdout
    again = _cli(lab, "models", "export-mlflow", "--tracking-uri", uri)
    assert again.returncode == 0 and "0 run(s) logged, 2 already there" in again.stdout, again.stdout

    client = mlflow.MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("vslab")
    assert experiment.artifact_location == (tmp_path / "artifacts").as_uri()  # beside the store, not ./mlruns
    runs = client.search_runs([experiment.experiment_id])
    models = model_store.list_models(lab / "models")
    assert sorted(r.data.tags[VERSION_TAG] for r in runs) == sorted(m["version"] for m in models)
    for run in runs:
        version = run.data.tags[VERSION_TAG]
        path = model_store.find(lab / "models", version)
        card = json.loads((path / model_store.CARD).read_text())
        assert run.info.status == "FINISHED" and run.data.tags[NAME_TAG] == card["name"]
        # parameters: the training configuration, flattened
        assert run.data.params["net.direction"] == card["train_config"]["net"]["direction"]
        assert run.data.params["seed"] == str(card["train_config"]["seed"])
        # metrics: the test summary and one per cell
        expected = run_metrics(card)
        assert any(k.startswith("test.cell.") for k in expected)
        for k, v in expected.items():
            assert run.data.metrics[k] == pytest.approx(v, rel=1e-12), k
        assert run.data.metrics["test.tip_mean_mm"] == pytest.approx(card["metrics"]["tip_mean_mm"])
        # learning curves as histories, one value per epoch
        history = client.get_metric_history(run.info.run_id, "val_loss")
        assert [m.step for m in sorted(history, key=lambda m: m.step)] == [c["epoch"] for c in card["curves"]]
        np.testing.assert_allclose([m.value for m in sorted(history, key=lambda m: m.step)],
                                   [c["val_loss"] for c in card["curves"]])  # fmt: skip
        # the files, byte for byte
        client.download_artifacts(run.info.run_id, "model", str(tmp_path / version))
        for name in (model_store.CARD, *model_store.FILES):
            assert (path / name).read_bytes() == (tmp_path / version / "model" / name).read_bytes(), name
        # the dataset as an input, its version id as digest
        (dataset,) = run.inputs.dataset_inputs
        assert (dataset.dataset.name, dataset.dataset.digest) == (card["dataset"]["name"],
                                                                  card["dataset"]["version"])  # fmt: skip


@pytest.mark.slow
def test_an_interrupted_export_is_replaced_not_duplicated(lab, tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = mlflow.MlflowClient(tracking_uri=uri)
    experiment_id = client.create_experiment("vslab", artifact_location=str(tmp_path / "artifacts"))
    version = model_store.list_models(lab / "models")[0]["version"]
    half = client.create_run(experiment_id, tags={VERSION_TAG: version})  # a run left RUNNING
    done = _cli(lab, "models", "export-mlflow", "--tracking-uri", uri)
    assert done.returncode == 0, done.stdout + done.stderr
    runs = client.search_runs([experiment_id], filter_string=f"tags.`{VERSION_TAG}` = '{version}'")
    assert len(runs) == 1 and runs[0].info.run_id != half.info.run_id and runs[0].info.status == "FINISHED"


@pytest.mark.slow
def test_the_default_store_lives_in_the_lab_and_errors_are_one_line(lab, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    done = _cli(lab, "models", "export-mlflow", env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (lab / "mlflow" / "mlflow.db").is_file()
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for args in (["--tracking-uri", f"sqlite:///{blocker}/x.db"], ["--tracking-uri", "nope://where"]):
        bad = _cli(lab, "models", "export-mlflow", *args)
        said = (bad.stdout + bad.stderr).strip().splitlines()
        assert bad.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), said


def _free_port() -> int:
    """A port on 127.0.0.1 that nothing listens on: bound here, then closed."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _one_error_line(done: subprocess.CompletedProcess) -> str:
    said = (done.stdout + done.stderr).strip().splitlines()
    assert done.returncode == 2 and len(said) == 1 and said[0].startswith("error:"), said
    return said[0]


@pytest.mark.slow
def test_an_mlflow_server_that_is_not_there_is_one_line_within_seconds(lab):
    uri = f"http://127.0.0.1:{_free_port()}"
    start = time.monotonic()
    # old code: MLflow's client retried the refused connection for about 4 minutes (247 s measured)
    done = _cli(lab, "models", "export-mlflow", "--tracking-uri", uri)
    elapsed = time.monotonic() - start
    line = _one_error_line(done)
    assert f"MLflow at {uri} does not answer" in line and "Connection refused" in line, line
    assert elapsed < 30, f"{elapsed:.1f} s to say the server is not there"  # 5 s probe + start-up, busy box


def test_any_http_reply_is_a_server_there():
    """The check before an export passes wherever an HTTP server answers, whatever it answers (here 404)."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        _reachable(f"http://127.0.0.1:{server.server_port}")
    finally:
        server.shutdown()
        server.server_close()
    with pytest.raises(MlflowExportError, match="does not answer within 1 s"):
        _reachable(f"http://127.0.0.1:{_free_port()}", timeout_s=1)


@contextlib.contextmanager
def _read_only(folder):
    """``folder`` read-only for this process. Root ignores permission bits, so as root the folder is made
    immutable (``chattr +i``, which stops root too); skipped where the file system has no such attribute."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        undo = ["chmod", "755", str(folder)]
    else:
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(folder)]).returncode:
            pytest.skip(
                "running as root, and chattr +i does not work here: no way to make a folder read-only"
            )
        undo = ["chattr", "-i", str(folder)]
    try:
        yield folder
    finally:
        subprocess.run(undo, check=True)


@pytest.mark.slow
def test_a_read_only_lab_is_one_line_naming_the_folder(lab, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    mine = tmp_path / "lab"
    mine.mkdir()
    (mine / "models").symlink_to(lab / "models")
    with _read_only(mine):  # no mlflow/ yet, and none can be made
        line = _one_error_line(_cli(mine, "models", "export-mlflow", env=env))
    assert f"{mine / 'mlflow'}: cannot be written" in line, line
    (mine / "mlflow").mkdir()
    with _read_only(mine / "mlflow"):  # the store's folder is there, read-only
        line = _one_error_line(_cli(mine, "models", "export-mlflow", env=env))
    assert f"{mine / 'mlflow'}: cannot be written" in line, line
    assert not (mine / "mlflow" / "mlflow.db").exists()
