"""The Dask set-up shared by the commands that spread work over processes (``batch``, ``fuse``)."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from ..errors import InvalidInputError

__all__ = ["ScatteringExecutor", "check_workers", "dask_client"]


def check_workers(n_workers: int | None) -> None:
    """Refuse a local cluster without workers (it would wait for ever)."""
    if n_workers is not None and (isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1):
        raise InvalidInputError(f"the number of workers must be an integer >= 1; got {n_workers!r}")


@contextmanager
def dask_client(scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Any]:
    """A ``dask.distributed`` client: of an existing scheduler, or of a local cluster started here.

    Parameters
    ----------
    scheduler : address of a running scheduler (``tcp://host:8786``); None starts a local
        cluster of ``n_workers`` single-threaded worker processes, closed on exit.
    n_workers : local workers (default: the number of CPU cores).
    """
    check_workers(n_workers)
    # Dask logs every worker start and stop at INFO; keep stderr for our own messages.
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    logging.getLogger("distributed").setLevel(logging.WARNING)
    from dask.distributed import Client, LocalCluster

    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            # the scheduler's HTTP server starts even without a dashboard; on a free port, not
            # 8787, so a second cluster on the machine does not print a port warning
            scheduler_kwargs={"dashboard_address": ":0"},
            silence_logs=logging.WARNING,
        )
    client = Client(scheduler if scheduler is not None else cluster)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


class ScatteringExecutor:
    """``map`` over a Dask client that sends each argument to the workers once, outside the task graph.

    ``client.get_executor().map`` embeds every argument in the graph, which the scheduler then
    handles as a whole ("Sending large graph"); for chunks of data, scattering them first and
    mapping over the futures is several times faster.  Results come back in order.
    """

    def __init__(self, client: Any) -> None:
        self._client = client

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        data = self._client.scatter(list(items))
        futures = self._client.map(fn, data, pure=False)
        return iter(self._client.gather(futures))
