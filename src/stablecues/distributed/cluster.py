"""Reaching a Dask cluster: a local one started for the job, or one already running somewhere.

``dask.distributed`` is an optional dependency (``pip install "stablecues[dask]"``); it is
imported when a cluster is asked for, never at import time.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from ..errors import ClusterError, ConfigError

log = logging.getLogger(__name__)

#: seconds to wait for a scheduler to answer, or for local workers to start
CONNECT_TIMEOUT_S = 60.0


#: a Dask scheduler's greeting (its handshake message) is a few hundred bytes
_MAX_GREETING = 1 << 20

__all__ = ["CONNECT_TIMEOUT_S", "ClusterError", "check_timeout", "open_client", "probe_scheduler",
           "worker_addresses"]


def check_timeout(value: float, what: str = "timeout") -> float:
    """``value`` when it is a finite number of seconds above 0."""
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{what}: expected a positive number of seconds, got {value!r}")
    return float(value)


def _read_exactly(sock: socket.socket, n: int, deadline: float) -> bytes:
    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError
        sock.settimeout(left)
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("the connection was closed")
        data += chunk
    return data


def probe_scheduler(address: str, timeout_s: float) -> None:
    """Check that a Dask scheduler answers at a ``tcp://host:port`` address within ``timeout_s``,
    before ``distributed`` connects: a Dask listener greets every connection with its handshake
    (a length, a frame count, frame lengths, frames), where another service sends nothing (the
    client would wait past any timeout) or text (read as a frame length of exabytes). Other
    schemes (tls, ucx, inproc) are left to ``distributed``.

    Raises:
        ClusterError: nothing answers, or what answers is not a Dask scheduler.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, loc = parse_address(address.strip())
    except ValueError as exc:
        raise ConfigError(f"scheduler address {address!r}: {exc}") from None
    if scheme != "tcp":
        return
    try:
        host, port = parse_host_port(loc)
    except ValueError as exc:
        raise ConfigError(f"scheduler address {address!r}: {exc}") from None
    deadline = time.monotonic() + timeout_s
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            head = _read_exactly(sock, 8, deadline)
            (total,) = struct.unpack("<Q", head)
            if not 16 <= total <= _MAX_GREETING:
                raise ClusterError(f"{address} answers, but not as a Dask scheduler (it sent "
                                   f"{head.decode('latin-1')!r}...)")
            body = _read_exactly(sock, total, deadline)
    except TimeoutError:
        raise ClusterError(f"{address}: no Dask scheduler answered within {timeout_s:g} s") from None
    except OSError as exc:
        raise ClusterError(f"cannot reach the scheduler at {address}: {exc.strerror or exc}") from None
    (n_frames,) = struct.unpack_from("<Q", body)
    lengths = struct.unpack_from(f"<{n_frames}Q", body, 8) if 0 < n_frames <= (total - 8) // 8 else None
    if lengths is None or 8 * (1 + n_frames) + sum(lengths) != total:
        raise ClusterError(f"{address} answers, but not as a Dask scheduler (its greeting is not Dask's)")


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
    timeout_s = check_timeout(timeout_s)
    if scheduler is not None:
        probe_scheduler(scheduler, timeout_s)
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
