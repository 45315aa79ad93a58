"""The lab on object storage: a real S3 endpoint (moto in server mode on 127.0.0.1, started and stopped here)
holds a whole lab — simulate → build → train → figures through the `vslab` command with ``--lab s3://…`` —
that gives the local lab's dataset and model versions and bit-identical weights. Credentials come from the
standard AWS environment only and appear in no object the lab writes. A half-uploaded entry is never
visible; an unreachable store, a missing bucket and a recording aimed at a store are one line each."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

pytest.importorskip("s3fs", reason="the [s3] extra (dev installs it)")
moto_server = pytest.importorskip("moto.server", reason="moto[server] (dev installs it)")

from conftest import absent_service_ports  # noqa: E402

from acquisition.storage import StoreError, check_store, lab_path, publish  # noqa: E402
from pipeline.dataset_store import DatasetStore  # noqa: E402
from pipeline.lab import Lab  # noqa: E402

SECRET = "vslab-test-secret-6d1f0c"  # must never appear in what the lab writes
KEY_ID = "vslab-test-key-id"
GRID = {
    "models": [{"direction": "forward", "preset": "small-residual", "hidden": [16, 16]},
               {"direction": "inverse", "preset": "paper", "hidden": [16, 16]}],
    "datasets": ["campaign"], "splits": ["split_random"], "seeds": [0],
    "train": {"max_epochs": 4, "patience": 4, "batch_size": 64},
}  # fmt: skip


@pytest.fixture(scope="module")
def s3():
    """An S3 endpoint on 127.0.0.1 with an empty bucket ``lab``; yields the environment a client needs (the
    standard AWS variables: nothing else tells vslab where the store is or who it is)."""
    logging.getLogger("werkzeug").setLevel(logging.WARNING)  # the server's line per request
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    # moto keeps its buckets in this process, across servers: empty them, or a second set-up of this module
    # in the same test worker (its tests run apart under xdist) finds the last one's bucket
    urllib.request.urlopen(urllib.request.Request(f"http://{host}:{port}/moto-api/reset", method="POST"))
    env = {"AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET, "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://{host}:{port}"}  # fmt: skip
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # this process's own clients (the checks below) read the same variables
    try:
        import s3fs

        s3fs.S3FileSystem.clear_instance_cache()
        s3fs.S3FileSystem().mkdir("lab")
        yield env
    finally:
        for k, v in saved.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
        server.stop()


def _vslab(env: dict, *args, timeout: float = 600) -> subprocess.CompletedProcess:
    """`vslab ARGS` in a fresh process with ``env`` (the AWS variables) added to this one's."""
    return subprocess.run([sys.executable, "-m", "vslab.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **env, "VSLAB_BATCH_NICE": "0",
                                                           "COLUMNS": "200"})  # fmt: skip


def _ok(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "Traceback" not in done.stdout + done.stderr, done.stderr[-3000:]
    return done.stdout


def _one_error_line(done: subprocess.CompletedProcess) -> str:
    out = done.stdout + done.stderr
    assert done.returncode == 2 and "Traceback" not in out, out
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), out
    return lines[0]


@pytest.mark.slow
def test_a_lab_on_s3_simulates_builds_trains_and_draws_as_a_local_lab_does(s3, tmp_path, campaign_dataset):
    src, local_version, _ = campaign_dataset  # the same campaign (seed 11, 600 points, 8 benches), local
    url = "s3://lab/run1"
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump(GRID))
    campaign = ["simulate", "campaign", "--seed", "11", "--benches", "8", "--set", "points=600"]
    simulated = _ok(_vslab(s3, "--lab", url, "--quiet", *campaign))
    assert "8 sessions written" in simulated and "s3://lab/run1/sessions" in simulated
    again = _ok(_vslab(s3, "--lab", url, "--quiet", *campaign))
    assert "0 sessions written, 8 already complete" in again  # the store's sessions are not simulated twice
    built = _ok(_vslab(s3, "--lab", url, "--quiet", "build"))
    assert f"dataset campaign {local_version}: built" in built  # the local build's version: same content
    assert "already built" in _ok(_vslab(s3, "--lab", url, "--quiet", "build"))
    trained = _ok(_vslab(s3, "--lab", url, "--quiet", "train", "--grid", grid, "--workers", "1"))
    assert "2 trained" in trained
    drawn = _ok(_vslab(s3, "--lab", url, "--quiet", "figures"))
    assert "report: s3://lab/run1/report/index.html" in drawn

    lab = lab_path(url)
    # the sessions, the dataset and its frame are the local lab's
    assert sorted(p.name for p in (lab / "sessions").iterdir()) == sorted(
        p.name for p in (src / "sessions").iterdir()
    )
    stored, _ = DatasetStore(lab / "datasets").load("campaign", local_version)
    local, _ = DatasetStore(src / "datasets").load("campaign", local_version)
    assert stored.equals(local)
    # the models: the versions and the weights' bytes a local run of the same grid gives
    from pipeline.grid import load_grid, run_grid

    mine = tmp_path / "local"
    mine.mkdir()
    (mine / "datasets").symlink_to(src / "datasets")
    results = run_grid(Lab(mine), load_grid(grid), threads=1)
    for r in results:
        on_s3 = lab / "models" / r["name"] / r["version"] / "weights.safetensors"
        assert (
            on_s3.read_bytes()
            == (mine / "models" / r["name"] / r["version"] / "weights.safetensors").read_bytes()
        )
    listed = _ok(_vslab(s3, "--lab", url, "models", "list"))
    assert all(r["version"] in listed for r in results)
    # the figures with their records, and the report linking their PDFs beside it
    figures = {p.name for p in (lab / "figures").iterdir()}
    assert {
        "error_heatmaps.png",
        "error_heatmaps.pdf",
        "error_heatmaps.json",
        "learning_curves.png",
    } <= figures
    page = (lab / "report" / "index.html").read_text()
    assert 'href="../figures/error_heatmaps.pdf"' in page and "data:image/png;base64," in page
    # no credential in anything the lab wrote (cards, records, metadata, the report)
    for path in lab.rglob("*"):
        if path.is_file() and path.suffix in (".json", ".html", ".mcap", ".yaml"):
            data = path.read_bytes()
            assert SECRET.encode() not in data and KEY_ID.encode() not in data, path


def test_a_half_uploaded_entry_is_never_visible(s3, monkeypatch):
    root = lab_path("s3://lab/torn") / "datasets"
    table = {"data": __import__("pandas").DataFrame({"split_random": ["train"], "x_0": [1.0]})}
    real_put = root.fs.put_file

    def put_file(local, remote, *a, **k):
        if remote.endswith("card.json"):  # the connection drops before the manifest goes up
            raise ConnectionError("the network went away")
        return real_put(local, remote, *a, **k)

    monkeypatch.setattr(root.fs, "put_file", put_file)
    with pytest.raises(ConnectionError):
        DatasetStore(root).write("d", "v1", table, {})
    assert (root / "d" / "v1" / "data.parquet").is_file()  # the data went up ...
    assert DatasetStore(root).newest("d") is None  # ... but no reader takes the version
    with pytest.raises(FileNotFoundError):
        DatasetStore(root).load("d", "v1")
    monkeypatch.setattr(root.fs, "put_file", real_put)
    DatasetStore(root).write("d", "v1", table, {})  # the next writer of the same content completes it
    store = DatasetStore(root)
    assert store.newest("d") == "v1" and store.load("d", "v1")[0]["x_0"].tolist() == [1.0]


def test_a_model_or_session_without_its_manifest_is_not_listed(s3):
    from acquisition.recorder.sessions import SessionStore
    from pipeline.model_store import list_models

    lab = lab_path("s3://lab/partial")
    (lab / "models" / "forward-x" / "0123abcd").mkdir(parents=True, exist_ok=True)
    (lab / "models" / "forward-x" / "0123abcd" / "weights.safetensors").write_bytes(b"half")
    (lab / "sessions" / "sim-a").mkdir(parents=True, exist_ok=True)
    (lab / "sessions" / "sim-a" / "sim-a_000.mcap").write_bytes(b"half")
    assert list_models(lab / "models") == []
    assert SessionStore(lab / "sessions").select("all") == ([], {})  # not even named as damaged: in transit


def test_publish_keeps_what_another_writer_published_first(s3):
    final = lab_path("s3://lab/race") / "entry"

    def fill(text):
        return lambda folder: [(folder / "a.txt").write_text(text), (folder / "record.json").write_text("{}")]

    assert publish(final, fill("first"), "record.json")
    assert not publish(final, fill("second"), "record.json")
    assert (final / "a.txt").read_text() == "first"


@pytest.mark.slow
def test_store_errors_are_one_line(s3, tmp_path):
    line = _one_error_line(_vslab(s3, "--lab", "s3://no-such-bucket/lab", "sessions", "list"))
    assert "the bucket 'no-such-bucket' does not exist" in line
    down = {**s3, "AWS_ENDPOINT_URL": "http://127.0.0.1:9", "AWS_MAX_ATTEMPTS": "1"}
    line = _one_error_line(_vslab(down, "--lab", "s3://lab/x", "models", "list", timeout=120))
    assert "does not answer" in line and "127.0.0.1:9" in line
    line = _one_error_line(_vslab(s3, "--lab", "nosuch://x/lab", "sessions", "list"))
    assert "cannot open this store" in line
    for command in (["record", "--duration", "1"], ["run", "experiment1", "--rig"], ["demo"]):
        line = _one_error_line(_vslab(s3, "--lab", "s3://lab/x", *command))
        assert "records into a local lab" in line and "sessions upload" in line, command
    with pytest.raises(StoreError, match="does not exist"):
        check_store(lab_path("s3://no-such-bucket/x"))


@pytest.mark.slow
def test_a_store_that_is_not_there_is_one_line_within_seconds(s3):
    """Nothing on the port (bound and closed), and a port that accepts but never answers, with botocore's and
    s3fs's own retries (no AWS_MAX_ATTEMPTS): one line naming the address, well within a minute (old code:
    retried for tens of seconds, and minutes on the silent port)."""
    with absent_service_ports() as ports:
        for port in ports:
            down = {**s3, "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}"}
            start = time.monotonic()
            line = _one_error_line(_vslab(down, "--lab", "s3://lab/x", "models", "list", timeout=120))
            elapsed = time.monotonic() - start
            assert "s3://lab/x: the store does not answer" in line and f"127.0.0.1:{port}" in line, line
            assert elapsed < 30, f"{elapsed:.1f} s to say the store at 127.0.0.1:{port} is not there"


@pytest.mark.slow
def test_local_sessions_are_uploaded_whole_and_never_replaced(s3, tmp_path, campaign_dataset):
    src, _, _ = campaign_dataset
    session = sorted((src / "sessions").iterdir())[0]
    url = "s3://lab/upload"
    out = _ok(_vslab(s3, "--lab", url, "sessions", "upload", session))
    assert f"{session.name}: uploaded" in out
    assert "already in the lab" in _ok(_vslab(s3, "--lab", url, "sessions", "upload", session))
    stored = lab_path(url) / "sessions" / session.name
    assert sorted(p.name for p in stored.iterdir()) == sorted(p.name for p in session.iterdir())
    assert json.loads((stored / "session.json").read_text()) == json.loads(
        (session / "session.json").read_text()
    )
    torn = tmp_path / "sim-torn"
    torn.mkdir()
    (torn / "session.json").write_text(
        json.dumps({"robot": "vsl", "experiment": "campaign", "status": "recording"})
    )
    (torn / "sim-torn_000.mcap").write_bytes(b"\x89MCAP0\r\n")
    other = sorted((src / "sessions").iterdir())[1]
    line = _one_error_line(_vslab(s3, "--lab", url, "sessions", "upload", other, torn))
    assert "not complete" in line
    for name in (other.name, "sim-torn"):  # every folder is checked before anything goes up
        assert not (lab_path(url) / "sessions" / name).exists(), name
    line = _one_error_line(_vslab(s3, "--lab", str(tmp_path / "local-lab"), "sessions", "upload", session))
    assert "local folder" in line


def test_a_local_lab_is_still_a_plain_path(tmp_path):
    assert isinstance(lab_path(tmp_path), Path) and isinstance(lab_path(str(tmp_path)), Path)
    assert lab_path(f"file://{tmp_path}") == tmp_path


@pytest.mark.slow
def test_a_cluster_builds_a_lab_on_s3_as_one_machine_does(s3, campaign_dataset):
    """The workers (processes of their own, as on other machines) reach the store through the same AWS
    environment, not through a shared file system."""
    from pipeline.cluster import local_cluster

    src, local_version, _ = campaign_dataset
    url = "s3://lab/cluster"
    _ok(_vslab(s3, "--lab", url, "--quiet", "sessions", "upload", *sorted((src / "sessions").iterdir())))
    with local_cluster(2, port=0) as cluster:  # started after the fixture set the AWS variables
        built = _ok(_vslab(s3, "--lab", url, "--quiet", "build", "--cluster", cluster.scheduler_address))
    assert f"dataset campaign {local_version}: built" in built and "(0 cached)" in built
    entries = list((lab_path(url) / "cache" / "session").iterdir())
    assert len(entries) == 8 and all((e / "record.json").is_file() for e in entries)  # written by the workers


def test_a_damaged_session_on_the_store_is_named_by_its_store_path(s3, campaign_dataset):
    from pipeline.build import process_session
    from pipeline.cache import StageCache

    src, _, _ = campaign_dataset
    good = sorted((src / "sessions").iterdir())[0]
    bad = lab_path("s3://lab/damaged/sessions/sim-bad")
    (bad / "session.json").write_bytes((good / "session.json").read_bytes())
    (bad / "sim-bad_000.mcap").write_bytes(b"not an MCAP file at all")
    result = process_session(
        bad, {"clean": {}, "segment": {}}, StageCache(lab_path("s3://lab/damaged/cache"))
    )
    assert "s3://lab/damaged/sessions/sim-bad/sim-bad_000.mcap" in result["error"], result
    assert "vslab-fetch" not in result["error"] and "not an MCAP file" in result["error"]


@pytest.mark.slow
def test_sessions_of_another_robot_on_the_store_are_refused_by_their_store_path(s3, tmp_path):
    """A store's twin sessions are checked through copies of their cards: a rerun with another robot is one
    line naming the store's sessions folder (not the local folder the run writes into), and nothing more."""
    url = "s3://lab/ident"
    small = ["simulate", "popup_impact", "--set", "pressures_kpa=[50]", "--set", "taps=1",
             "--set", "settle_s=0.5", "--set", "record_s=0.5"]  # fmt: skip
    assert "1 sessions written" in _ok(_vslab(s3, "--lab", url, "--quiet", *small))
    robot = tmp_path / "popup_perturbed.yaml"
    robot.write_text("extends: popup\nservo: {torque_constant_nm_per_a: 9.0}\n")
    line = _one_error_line(_vslab(s3, "--lab", url, "--quiet", *small, "--set", f"robot={robot}"))
    assert f"in {url}/sessions have this run's ids" in line and "differs: robot description" in line, line
    assert "vslab-sessions-" not in line
