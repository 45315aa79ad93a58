"""A Dask cluster as the pipeline's executor (the optional extra ``vslab[cluster]``).

`vslab build` and `vslab train` run their per-job functions (``build.process_session``, ``grid.train_job``)
through any ``concurrent.futures.Executor``. Dask distributed's ``Client.get_executor`` is one: the same jobs
go to a scheduler's workers on other machines, each retried on another worker when the one running it dies.
Results do not depend on where a job ran (a job is a pure function of its inputs and seed), so a build or a
grid gives the same versions and the same weights on a cluster as on one machine.

The workers must see the lab at the same path as the client (a shared file system), or the same store
(``--lab s3://…``, reached with the same AWS environment: a job receives the lab's URL, never credentials);
each trains with one torch thread, so a worker per core never oversubscribes its machine.

    with cluster_executor("tcp://10.0.0.5:8786") as executor:
        build(sessions, lab, "campaign", executor=executor)

``local_cluster`` starts a cluster of worker processes on this machine (`vslab cluster local`), to try it.
"""

from __future__ import annotations

import contextlib
import gc
import sys
from collections.abc import Iterator

from pipeline.errors import PipelineError

RETRIES = 2  # a job whose worker died runs again on another, up to this many times
CONNECT_TIMEOUT_S = 5.0


class ClusterError(PipelineError, RuntimeError):
    """No cluster to run on: Dask distributed is not installed, or no scheduler answers at the address."""


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ClusterError(
            "a cluster needs Dask distributed, an optional extra: pip install 'vslab[cluster]'"
        ) from None
    return distributed


@contextlib.contextmanager
def cluster_executor(
    address: str, retries: int = RETRIES, timeout_s: float = CONNECT_TIMEOUT_S
) -> Iterator[object]:
    """A ``concurrent.futures``-style executor on the Dask scheduler at ``address`` (``tcp://host:port``),
    closed on exit; :class:`ClusterError` when none answers within ``timeout_s``."""
    distributed = _distributed()
    client, why = None, ""
    try:
        _handshake(distributed, address, timeout_s)
        client = distributed.Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        said = f"{type(exc).__name__}: {exc}" if str(exc) else "connected, but no handshake came"
        why = f"no Dask scheduler answers at {address!r} within {timeout_s:g} s ({said})"
    except (ValueError, TypeError) as exc:  # not an address
        why = f"no Dask scheduler at {address!r}: {exc} (an address is tcp://host:port)"
    if client is None:
        _collect_quietly()
        raise ClusterError(f"{why}; check the address, or start one: `vslab cluster local`")
    try:
        # pure=False: every submission is its own task (a retried job is the same task run again)
        yield client.get_executor(retries=retries, pure=False)
    finally:
        client.close()


def _handshake(distributed, address: str, timeout_s: float) -> None:
    """Connect to ``address`` and exchange Dask's handshake within ``timeout_s``, then hang up. The Client
    bounds its connect, not the handshake after it: a port that accepts but never speaks (no scheduler
    behind it) would hold it for ever."""
    import asyncio

    args = distributed.Security().get_connection_args("client")  # tls:// as the Client would reach it

    async def shake() -> None:
        comm = await distributed.comm.connect(address, timeout=timeout_s, **args)
        await comm.close()

    asyncio.run(asyncio.wait_for(shake(), timeout_s))


def _collect_quietly() -> None:
    """Collect the client that failed to connect now: its finaliser tries to close a connection that never
    opened and would print that failure's traceback at exit, after the one clear error line."""
    hook = sys.unraisablehook
    sys.unraisablehook = lambda _: None
    try:
        gc.collect()
    finally:
        sys.unraisablehook = hook


def local_cluster(workers: int, host: str = "127.0.0.1", port: int = 0):
    """A started ``distributed.LocalCluster`` of ``workers`` processes with one thread each (close it, or use
    it as a context manager). ``port`` 0: any free port (its ``scheduler_address`` says which)."""
    distributed = _distributed()
    if workers < 1:
        raise ValueError(f"a cluster needs at least 1 worker, got {workers}")
    # the scheduler's HTTP routes (health, metrics, a dashboard where bokeh is installed) on a free port:
    # the default, 8787, is taken by a second cluster on the machine
    return distributed.LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, host=host, scheduler_port=port,
        dashboard_address=f"{host}:0",
    )  # fmt: skip
