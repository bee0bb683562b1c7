"""The Dask set-up shared by the commands that spread work over processes (``batch``, ``fuse``, ``reconstruct IMAGES``)."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from ..errors import InvalidInputError

__all__ = ["ScatteringExecutor", "check_cluster", "dask_client", "executor_for"]


def check_cluster(
    scheduler: str | None,
    n_workers: int | None,
    *,
    scheduler_name: str = "scheduler",
    workers_name: str = "n_workers",
) -> None:
    """Check where Dask work is to run: an existing scheduler, or a local cluster of ``n_workers``.

    The one check of these two options, for the library (:func:`dask_client`,
    ``run_batch``, ``run_fuse``) and the command line alike.

    Parameters
    ----------
    scheduler : str or None
        Address of an existing scheduler, or None.
    n_workers : int or None
        Processes of a local cluster (None: the number of CPU cores).
    scheduler_name, workers_name : str
        How the error message names the two options (the CLI passes ``--scheduler``
        and ``--workers``).

    Raises
    ------
    InvalidInputError
        ``n_workers`` is not an integer >= 1 (a local cluster without workers would wait
        for ever), or both are given (a local cluster's size means nothing to an existing one).

    Examples
    --------
    >>> check_cluster(None, 2)
    >>> check_cluster("tcp://host:8786", 2)
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: give n_workers (a local cluster) or scheduler (an existing one), not both
    """
    if n_workers is not None and (isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1):
        raise InvalidInputError(f"{workers_name} must be an integer >= 1; got {n_workers!r}")
    if scheduler is not None and n_workers is not None:
        raise InvalidInputError(
            f"give {workers_name} (a local cluster) or {scheduler_name} (an existing one), not both"
        )


@contextmanager
def dask_client(scheduler: str | None = None, n_workers: int | None = None,
                connect_timeout_s: float = 10.0) -> Iterator[Any]:
    """A ``dask.distributed`` client: of an existing scheduler, or of a local cluster started here.

    Enter it before any output folder is made: a scheduler that cannot be reached is the
    user's to fix, one line and nothing written.

    Parameters
    ----------
    scheduler : address of a running scheduler (``tcp://host:8786``); None starts a local
        cluster of ``n_workers`` single-threaded worker processes, closed on exit.
    n_workers : local workers (default: the number of CPU cores).
    connect_timeout_s : how long to try to reach ``scheduler``.

    Raises
    ------
    InvalidInputError
        ``n_workers`` below 1 or given with ``scheduler`` (:func:`check_cluster`), or
        ``scheduler`` is not an address or cannot be reached.
    """
    check_cluster(scheduler, n_workers)
    with _dask_quiet():
        yield from _client(scheduler, n_workers, connect_timeout_s)


@contextmanager
def executor_for(scheduler: str | None, n_workers: int | None) -> Iterator[ScatteringExecutor | None]:
    """A :class:`ScatteringExecutor` on :func:`dask_client` when ``scheduler`` or ``n_workers`` is given; else None
    (the work then runs in this process, as the estimators do by default).

    Examples
    --------
    >>> with executor_for(None, None) as executor:
    ...     executor is None
    True
    """
    if scheduler is None and n_workers is None:
        yield None
        return
    with dask_client(scheduler, n_workers) as client:
        yield ScatteringExecutor(client)


#: Dask's loggers, kept to errors while kalmansfm uses a cluster: its INFO lines tell every worker start and
#: stop, and its WARNINGs ("Worker process still alive after 4.0 seconds, killing" when a loaded machine is slow
#: to stop a worker at the end of a successful run) are about its own housekeeping, not the user's results.
_DASK_LOGGERS = ("distributed", "dask", "bokeh", "tornado")


@contextmanager
def _dask_quiet() -> Iterator[None]:
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")  # read by worker processes as they start
    loggers = [logging.getLogger(name) for name in _DASK_LOGGERS]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _client(scheduler: str | None, n_workers: int | None, connect_timeout_s: float) -> Iterator[Any]:
    from dask.distributed import Client, LocalCluster

    cluster = None
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=connect_timeout_s)
        except (OSError, ValueError, TypeError) as exc:  # TimeoutError is an OSError
            reason = str(exc).rstrip(".") or type(exc).__name__
            raise InvalidInputError(f"cannot use the Dask scheduler {scheduler!r}: {reason}") from None
    else:
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            # the scheduler's HTTP server starts even without a dashboard; on a free port, not
            # 8787, so a second cluster on the machine does not print a port warning
            scheduler_kwargs={"dashboard_address": ":0"},
            silence_logs=logging.ERROR,
            # each worker ignores Ctrl-C (this process stops the cluster) and logs errors only
            preload=["kalmansfm.pipeline._dask_worker"],
        )
        try:
            client = Client(cluster)
        except BaseException:
            cluster.close()
            raise
    _quiet_interrupted_waits(client)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _quiet_interrupted_waits(client: Any) -> None:
    """Drop what the client's event loop reports about waits that a closed client ended.

    After Ctrl-C during ``gather`` the client closes while it still waits for each result;
    each wait then ends with Dask's ``AllExit``, and asyncio reports every such task
    ("Task exception was never retrieved", 5 lines each, 240 lines for 48 chunks) when it is
    collected.  Other reports of that loop pass unchanged.
    """
    loop = getattr(getattr(client, "loop", None), "asyncio_loop", None)
    if loop is None:
        return

    def report(event_loop: Any, context: dict[str, Any]) -> None:
        exception = context.get("exception")
        if type(exception).__name__ == "AllExit" or isinstance(exception, KeyboardInterrupt):
            return
        event_loop.default_exception_handler(context)

    loop.set_exception_handler(report)


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
