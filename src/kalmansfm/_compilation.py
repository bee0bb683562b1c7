"""One line when kalmansfm compiles its numba kernels, the first time they run on a machine.

numba compiles a kernel on its first call and keeps the machine code in its cache
(``cache=True``: ``__pycache__`` next to the source, or ``NUMBA_CACHE_DIR``, or the user's
cache directory when the package is read-only); later processes load it in milliseconds.
A compilation takes seconds during which nothing else moves, so the first one of a
process logs :data:`MESSAGE` once, at INFO level, on the ``kalmansfm`` logger: the
command line shows it on stderr (not with ``--quiet``), a library user sees it only if
they show that logger's INFO lines.  A process that loads every kernel from the cache
logs nothing: numba announces only real compilations (its ``numba:compile`` event).

The kernel modules call :func:`watch_compilation` when they are imported; the watch
covers every kernel whose module is part of kalmansfm, wherever it lives.
"""

from __future__ import annotations

import logging
import sys
import threading
from contextlib import nullcontext

from numba.core import event

__all__ = ["MESSAGE", "watch_compilation"]

#: The line logged on the first compilation of a kalmansfm kernel in a process.
MESSAGE = ("compiling numerical kernels for this machine, once: about 2–10 s per kind of run "
           "(later runs load them from the cache)")

_log = logging.getLogger("kalmansfm")
_lock = threading.Lock()
_state = {"watching": False, "announced": False}


def _ours(dispatcher: object) -> bool:
    module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
    return module == "kalmansfm" or module.startswith("kalmansfm.")


def _announce() -> None:
    """Log :data:`MESSAGE`; a progress bar on stderr is cleared first and drawn again after it."""
    try:
        from tqdm import tqdm

        around_bars = tqdm.external_write_mode(file=sys.stderr)
    except ImportError:  # pragma: no cover - tqdm is a dependency
        around_bars = nullcontext()
    with around_bars:
        _log.info(MESSAGE)


class _FirstCompilation(event.Listener):
    """Logs once per process, when numba starts compiling a kalmansfm kernel (not on a cache hit)."""

    def on_start(self, ev: event.Event) -> None:
        if _state["announced"] or not _ours(ev.data.get("dispatcher")):
            return
        with _lock:
            if _state["announced"]:
                return
            _state["announced"] = True
        _announce()

    def on_end(self, ev: event.Event) -> None:
        pass


def watch_compilation() -> None:
    """Start watching numba's compilations (once per process; later calls do nothing).

    Examples
    --------
    >>> watch_compilation()
    >>> watch_compilation()   # idempotent
    """
    with _lock:
        if _state["watching"]:
            return
        _state["watching"] = True
    event.register("numba:compile", _FirstCompilation())
