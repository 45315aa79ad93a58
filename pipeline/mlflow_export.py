"""``vslab models export-mlflow``: every saved model version as one MLflow run (the optional
extra ``vslab[mlflow]``).

A run holds the version's training parameters (flattened: ``net.hidden``, ``lr`` …), its test metrics (and
one metric per pressure × payload cell: ``test.cell.<bin>.<payload>g.tip_mm_mean``), its learning curves as
metric histories (``train_loss``, ``val_loss``, ``val_error_mm`` by epoch), its card, weights and ONNX file as
artifacts (``model/``) and its dataset as an input (name, version id as digest, the dataset's folder as
source). The run is tagged with the version id: exporting again skips what is there (a run an interrupted
export left unfinished is replaced), so nothing is duplicated. The model store stays the record; MLflow is a
view.
"""

from __future__ import annotations

import datetime
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.model_store import CARD, FILES, ModelIntegrityError, check_model, version_dirs

VERSION_TAG = "vslab.model_version"
NAME_TAG = "vslab.model_name"
DATASET_TAG = "vslab.dataset_version"
EXPERIMENT = "vslab"
PROBE_TIMEOUT_S = 5.0  # connect and read timeouts of the check that an MLflow server is there
BATCH = 100  # MLflow's log_batch takes at most 100 params (and 1000 metrics) per call
_UNSAFE = re.compile(r"[^0-9A-Za-z_.\-/ ]")  # characters MLflow refuses in a key


class MlflowExportError(PipelineError, RuntimeError):
    """MLflow is not installed, or its tracking store refused the export."""


@dataclass
class ExportReport:
    tracking_uri: str
    experiment: str
    logged: list[str] = field(default_factory=list)  # name/version
    skipped: list[str] = field(default_factory=list)  # already a finished run
    damaged: list[str] = field(default_factory=list)  # "name/version: why" (not exported)


def _client(tracking_uri: str):
    try:
        from mlflow import MlflowClient
    except ImportError:
        raise MlflowExportError(
            "MLflow is not installed: pip install 'vslab[mlflow]' (the MLflow client and its SQLite store)"
        ) from None
    _reachable(tracking_uri)
    return MlflowClient(tracking_uri=tracking_uri)


def _reachable(tracking_uri: str, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Raise :class:`MlflowExportError` unless the server of an ``http(s)://`` tracking URI answers within
    ``timeout_s``: MLflow's client retries a refused connection for about 4 minutes (7 retries, backoff 2 s,
    MLFLOW_HTTP_REQUEST_MAX_RETRIES) and waits 120 s per attempt. Any HTTP reply will do (the export itself
    then runs with MLflow's retries)."""
    if not tracking_uri.startswith(("http://", "https://")):
        return
    import requests

    try:  # MLflow's health route; whatever the reply, a server is there
        requests.get(f"{tracking_uri.rstrip('/')}/health", timeout=timeout_s)
    except requests.exceptions.SSLError:
        return  # a TLS server answered (its certificate is the export's business, not the probe's)
    except requests.exceptions.RequestException as exc:
        errno = re.search(r"\[Errno -?\d+\] [^'\")]*", str(exc))  # "[Errno 111] Connection refused"
        why = errno.group(0) if errno else type(exc).__name__
        raise MlflowExportError(
            f"MLflow at {tracking_uri} does not answer within {timeout_s:g} s ({why}): start the tracking "
            "server, or give another --tracking-uri"
        ) from None


def flatten(tree: Mapping, prefix: str = "") -> Iterator[tuple[str, object]]:
    """(dotted key, leaf) of a nested mapping: ``{"net": {"hidden": 64}}`` → ``("net.hidden", 64)``."""
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from flatten(value, f"{name}.")
        else:
            yield name, value


def _key(name: str) -> str:
    return _UNSAFE.sub("_", name)


def _number(value) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def run_metrics(card: dict) -> dict[str, float]:
    """The card's test metrics as MLflow metrics: the scalars as ``test.<name>``, each cell's means as
    ``test.cell.<pressure bin>.<payload>g.<name>``."""
    metrics = card.get("metrics") or {}
    out = {}
    for k, value in metrics.items():
        if (v := _number(value)) is not None:
            out[f"test.{_key(k)}"] = v
    for cell in metrics.get("per_cell") or []:
        where = f"test.cell.{_key(str(cell.get('pressure_bin')))}.{cell.get('payload_g')}g"
        for k, v in cell.items():
            if k.endswith("_mean") or k == "n":
                if (v := _number(v)) is not None:
                    out[f"{where}.{_key(k)}"] = v
    return out


def export_models(
    models_root: Path,
    datasets_root: Path,
    tracking_uri: str,
    experiment: str = EXPERIMENT,
    artifact_location: str | None = None,
) -> ExportReport:
    """Log every model version under ``models_root`` that the tracking store lacks as a run of ``experiment``
    (created with ``artifact_location`` if new). A damaged version is reported, not exported."""
    report = ExportReport(tracking_uri, experiment)
    try:
        client = _client(tracking_uri)
        found = client.get_experiment_by_name(experiment)
        experiment_id = (
            found.experiment_id
            if found is not None
            else client.create_experiment(experiment, artifact_location=artifact_location)
        )
        for path in version_dirs(models_root):
            where = f"{path.parent.name}/{path.name}"
            try:
                card = check_model(path)
            except ModelIntegrityError as exc:
                report.damaged.append(f"{where}: {exc.reason}")
                continue
            if _finished_run(client, experiment_id, card["version"]):
                report.skipped.append(where)
                continue
            _log_run(client, experiment_id, path, card, datasets_root)
            report.logged.append(where)
    except MlflowExportError:
        raise
    except Exception as exc:  # the store's own errors (MlflowException, OSError, a refused connection)
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise MlflowExportError(f"MLflow at {tracking_uri} refused the export: {first}") from exc
    return report


def _finished_run(client, experiment_id: str, version: str) -> bool:
    """Whether a finished run of ``version`` is there; unfinished ones (an interrupted export) are deleted."""
    runs = client.search_runs([experiment_id], filter_string=f"tags.`{VERSION_TAG}` = '{version}'")
    finished = False
    for run in runs:
        if run.info.status == "FINISHED" and not finished:
            finished = True
        else:
            client.delete_run(run.info.run_id)
    return finished


def _log_run(client, experiment_id: str, path: Path, card: dict, datasets_root: Path) -> None:
    from mlflow.entities import Dataset, DatasetInput, InputTag, Metric, Param

    dataset = card.get("dataset") or {}
    started = _millis(card.get("created"))
    run = client.create_run(
        experiment_id,
        start_time=started,
        run_name=f"{card['name']}/{card['version']}",
        tags={
            VERSION_TAG: card["version"],
            NAME_TAG: card["name"],
            DATASET_TAG: f"{dataset.get('name')}@{dataset.get('version')}",
            "mlflow.note.content": f"vslab model {card['name']}/{card['version']} ({path})",
        },
    )
    run_id = run.info.run_id
    params = [Param(_key(k), str(v)[:6000]) for k, v in flatten(card.get("train_config") or {})]
    params += [Param(k, str(card[k])) for k in ("best_epoch", "threads", "n_train", "n_val") if k in card]
    metrics = [Metric(k, v, started, 0) for k, v in run_metrics(card).items()]
    for epoch in card.get("curves") or []:
        for k in ("train_loss", "val_loss", "val_error_mm"):
            if (v := _number(epoch.get(k))) is not None:
                metrics.append(Metric(k, v, started, int(epoch["epoch"])))
    for k in ("train_time_s", "epoch_time_s"):
        if (v := _number(card.get(k))) is not None:
            metrics.append(Metric(k, v, started, 0))
    for i in range(0, max(len(params), len(metrics)), BATCH):
        client.log_batch(run_id, metrics=metrics[i : i + BATCH], params=params[i : i + BATCH])
    source = Path(str(datasets_root)) / str(dataset.get("name")) / str(dataset.get("version"))
    data = Dataset(
        name=str(dataset.get("name")),
        digest=str(dataset.get("version"))[:36],
        source_type="local",
        source=str(source),
        schema=None,
        profile=None,
    )
    client.log_inputs(run_id, datasets=[DatasetInput(data, [InputTag("mlflow.data.context", "training")])])
    for name in (CARD, *FILES):  # model/card.json, model/weights…, model/export/model.onnx
        if (path / name).is_file():
            client.log_artifact(run_id, str(path / name), "/".join(["model", *Path(name).parts[:-1]]))
    client.set_terminated(run_id, "FINISHED")


def _millis(created) -> int:
    """A card's ISO creation time in ms since the epoch (now, if it has none)."""
    try:
        when = datetime.datetime.fromisoformat(str(created))
    except ValueError:
        when = datetime.datetime.now(datetime.UTC)
    return int(when.timestamp() * 1000)
