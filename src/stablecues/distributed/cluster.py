"""Reaching a Dask cluster: a local one started for the job, or one already running somewhere.

``dask.distributed`` is an optional dependency (``pip install "stablecues[dask]"``); it is
imported when a cluster is asked for, never at import time.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from ..errors import ClusterError, ConfigError

log = logging.getLogger(__name__)

#: seconds to wait for a scheduler to answer, or for local workers to start
CONNECT_TIMEOUT_S = 60.0


__all__ = ["CONNECT_TIMEOUT_S", "ClusterError", "open_client", "worker_addresses"]


@contextmanager
def open_client(
    scheduler: str | None = None,
    *,
    workers: int = 2,
    threads_per_worker: int = 1,
    timeout_s: float = CONNECT_TIMEOUT_S,
) -> Iterator[Any]:
    """A ``distributed.Client`` for the duration of a ``with`` block; closed (with the local
    cluster it started, if any) when the block ends.

    Args:
        scheduler: address of a running scheduler (``tcp://host:8786``); None starts a
            ``LocalCluster`` of worker processes on this machine.
        workers: worker processes of the local cluster (ignored with ``scheduler``).
        threads_per_worker: threads of each local worker (1: one task at a time per process).
        timeout_s: how long to wait for the scheduler or the local workers.

    Yields:
        the connected client.

    Raises:
        ConfigError: ``workers`` or ``threads_per_worker`` below 1, or an address that is not text.
        ClusterError: the scheduler does not answer, or the local cluster does not start.
    """
    from distributed import Client, LocalCluster

    if workers < 1 or threads_per_worker < 1:
        raise ConfigError(f"a cluster needs at least one worker and one thread each, got {workers} x "
                          f"{threads_per_worker}")
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
        raise ConfigError(f"scheduler address: expected text such as tcp://host:8786, got {scheduler!r}")
    cluster: Any = None
    try:
        if scheduler is None:
            cluster = LocalCluster(n_workers=workers, processes=True, threads_per_worker=threads_per_worker,
                                   dashboard_address=":0")
            client = Client(cluster, timeout=timeout_s)
        else:
            client = Client(scheduler.strip(), timeout=timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:  # distributed's connect errors are OSErrors
        if cluster is not None:
            cluster.close()
        where = "a local cluster" if scheduler is None else f"the scheduler at {scheduler}"
        raise ClusterError(f"cannot reach {where}: {' '.join(str(exc).split())}") from exc
    try:
        log.info("dask scheduler %s, %d workers", scheduler or cluster.scheduler_address,
                 len(client.scheduler_info().get("workers", {})))
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def worker_addresses(client: Any, least: int = 1, timeout_s: float = CONNECT_TIMEOUT_S) -> list[str]:
    """Addresses of the cluster's workers, sorted; waits until at least ``least`` are there.

    Raises:
        ClusterError: fewer than ``least`` workers after ``timeout_s``.
    """
    try:
        client.wait_for_workers(least, timeout=timeout_s)
    except TimeoutError as exc:
        have = len(client.scheduler_info().get("workers", {}))
        raise ClusterError(f"the cluster has {have} workers after {timeout_s:.0f} s, {least} needed") from exc
    return sorted(client.scheduler_info()["workers"])
