"""Dask stays quiet: Ctrl-C while workers compute is one line, and stopping busy workers prints nothing.

Issue 30: Ctrl-C during ``fuse --workers 2`` printed about 40 lines of worker tracebacks (the
terminal sends SIGINT to every process of the group) and 240 lines of "Task exception was
never retrieved"; a successful run on a loaded machine printed Dask's "Worker process still
alive after 4.0 seconds, killing".
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kalmansfm.pipeline import _dask_worker
from kalmansfm.pipeline.cluster import _quiet_interrupted_waits

SRC = Path(__file__).resolve().parents[2] / "src"

DRIVER = """
import pathlib, sys, time
from kalmansfm.pipeline.cluster import ScatteringExecutor, dask_client

def slow(path):
    import pathlib, time
    pathlib.Path(path).touch()
    time.sleep(60)
    return path

try:
    with dask_client(n_workers=2) as client:      # closing it stops two workers in the middle of a task
        list(ScatteringExecutor(client).map(slow, [sys.argv[1]] * 8))
except KeyboardInterrupt:
    print("driver: interrupted", file=sys.stderr)
    sys.exit(130)
"""


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="process groups and signals are POSIX")
def test_ctrl_c_to_the_whole_process_group_while_workers_compute_is_one_line(tmp_path):
    marker = tmp_path / "started"
    process = subprocess.Popen(
        [sys.executable, "-c", DRIVER, str(marker)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(SRC)}, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while not marker.exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.1)
    assert marker.exists(), process.communicate()
    time.sleep(0.5)
    os.killpg(process.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the workers get it too
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert err.splitlines() == ["driver: interrupted"], err


def test_a_worker_ignores_ctrl_c_and_logs_errors_only():
    previous = signal.getsignal(signal.SIGINT)
    try:
        _dask_worker.dask_setup(worker=None)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_the_loop_drops_only_the_waits_a_closed_client_ended(capsys):
    class AllExit(Exception):  # distributed.client.AllExit, by name
        pass

    loop = asyncio.new_event_loop()
    reported = []
    loop.default_exception_handler = lambda context: reported.append(context["message"])  # type: ignore[method-assign]

    class Client:
        class loop:  # the shape of distributed's IOLoop wrapper
            asyncio_loop = None

    client = Client()
    client.loop.asyncio_loop = loop
    try:
        _quiet_interrupted_waits(client)
        loop.call_exception_handler({"message": "Task exception was never retrieved", "exception": AllExit()})
        loop.call_exception_handler({"message": "a real problem", "exception": ValueError("x")})
    finally:
        loop.close()
    assert reported == ["a real problem"]
