"""`vslab cluster`: a Dask cluster for `vslab build --cluster` and `vslab train --cluster` (an extra)."""

from __future__ import annotations

import time
from typing import Annotated

import typer

from vslab.app import _error, app, console

cluster_app = typer.Typer(help="A Dask cluster to build and train on (vslab[cluster]).", no_args_is_help=True)
app.add_typer(cluster_app, name="cluster")


@cluster_app.command("local")
def local(
    workers: Annotated[int, typer.Option(help="Worker processes (one thread each).")] = 2,
    host: Annotated[str, typer.Option(help="Address the scheduler listens on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Scheduler port (0: any free one).")] = 8786,
) -> None:
    """Start a cluster of worker processes on this machine and print its address; Ctrl-C stops it."""
    from pipeline.cluster import ClusterError, local_cluster

    if workers < 1:
        _error(f"--workers must be ≥ 1, got {workers}")
    if not 0 <= port <= 65535:
        _error(f"--port must be 0-65535, got {port}")
    try:
        cluster = local_cluster(workers, host=host, port=port)
    except ClusterError as exc:
        _error(str(exc))
    except (OSError, RuntimeError) as exc:  # the port taken, an address this machine does not have
        _error(f"cannot start a cluster on {host}:{port}: {exc}")
    with cluster:
        console.print(f"Dask scheduler at {cluster.scheduler_address} with {workers} workers; "
                      f"--cluster {cluster.scheduler_address}; Ctrl-C stops it", soft_wrap=True)  # fmt: skip
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            console.print("cluster stopped")
