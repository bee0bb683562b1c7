"""Loaded by every worker process of a local Dask cluster that kalmansfm starts (Dask's "preload" hook).

A Ctrl-C at the terminal reaches every process of the foreground group: the workers too,
which then printed a traceback each (about 40 lines for two workers).  The command line
process alone handles the interrupt and shuts the cluster down, so the workers ignore
SIGINT; Dask's own log lines in the worker are kept to errors.
"""

from __future__ import annotations

import logging
import signal
import threading
from typing import Any


def dask_setup(worker: Any) -> None:
    """Dask calls this in each worker process as it starts."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(logging.ERROR)
