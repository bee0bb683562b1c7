"""Atomic output: files appear complete or not at all.

Every file is written under a temporary name in its destination folder and
renamed over the final name only when the whole run succeeded, so a failed or
interrupted run never leaves a half-written file and never destroys the
results of an earlier run.
"""

from __future__ import annotations

import os
import shutil
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import InvalidInputError

__all__ = ["OutputDirectory", "output_directory", "atomic_write", "check_output_directory"]


def _temporary_name(final: Path) -> Path:
    return final.with_name(f".{final.name}.{uuid.uuid4().hex[:8]}.tmp")


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` and rename the result to ``path``; remove it on failure.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write(d / "a.txt", lambda p: p.write_text("hi")).read_text()
    'hi'
    """
    final = Path(path)
    tmp = _temporary_name(final)
    try:
        write(tmp)
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
    return final


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold SIGINT back for the duration of the block; raise KeyboardInterrupt after it if one came."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread receives signals (and may set handlers)
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
    if received:
        raise KeyboardInterrupt


class OutputDirectory:
    """Stages the files of one run; :meth:`commit` renames them into place together."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._staged: dict[Path, Path] = {}

    def file(self, name: str) -> Path:
        """A temporary path to write ``name`` to; it becomes ``path / name`` at commit."""
        final = self.path / name
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = self._staged.get(final) or _temporary_name(final)
        self._staged[final] = tmp
        return tmp

    def write_text(self, name: str, text: str) -> Path:
        """Stage a text file."""
        tmp = self.file(name)
        tmp.write_text(text, encoding="utf-8")
        return self.path / name

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Stage a binary file."""
        tmp = self.file(name)
        tmp.write_bytes(data)
        return self.path / name

    def commit(self) -> list[Path]:
        """Rename every staged file to its final name.

        A Ctrl-C that arrives during the renames is held back until they are all
        done (then raised), so that the folder never mixes old and new files.
        """
        done = []
        with _sigint_deferred():
            for final, tmp in self._staged.items():
                if tmp.exists():
                    os.replace(tmp, final)
                    done.append(final)
            self._staged.clear()
        return done

    def discard(self) -> None:
        """Delete every staged temporary file."""
        for tmp in self._staged.values():
            tmp.unlink(missing_ok=True)
        self._staged.clear()


def check_output_directory(path: str | os.PathLike[str]) -> Path:
    """Raise :class:`InvalidInputError` if ``path`` cannot become a run's output folder; create nothing.

    Call it before a long computation so that a typo in ``--out`` is reported at
    once rather than after the work.  :func:`output_directory` checks again (and
    for real, by writing a probe file) when the results are written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "notes.txt").write_text("x")
    >>> check_output_directory(d / "new" / "run") == d / "new" / "run"
    True
    >>> check_output_directory(d / "notes.txt" / "run")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: output folder ... is not writable (... is a file, not a folder)
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise InvalidInputError(f"output folder {folder} exists and is not a folder")
    existing = next((p for p in [folder, *folder.parents] if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InvalidInputError(f"output folder {folder} is not writable ({existing} is a file, not a folder)")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidInputError(f"output folder {folder} is not writable (no write permission in {existing})")
    return folder


@contextmanager
def output_directory(path: str | os.PathLike[str]) -> Iterator[OutputDirectory]:
    """Context manager for a run's output folder.

    The folder is created if needed and checked to be writable before any work
    is done.  Files staged through the yielded :class:`OutputDirectory` are
    renamed into place when the block succeeds; on an exception (including
    Ctrl-C) they are deleted, a folder this call created is removed again, and
    the exception propagates.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> with output_directory(d) as out:
    ...     _ = out.write_text("result.csv", "a,b\\n1,2\\n")
    >>> sorted(p.name for p in d.iterdir())
    ['result.csv']
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise InvalidInputError(f"output folder {folder} exists and is not a folder")
    created = []
    for parent in [folder, *folder.parents]:
        if parent.exists():
            break
        created.append(parent)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = _temporary_name(folder / "probe")
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        for c in created:
            shutil.rmtree(c, ignore_errors=True)
        raise InvalidInputError(f"output folder {folder} is not writable ({exc.strerror or exc})") from None
    out = OutputDirectory(folder)
    try:
        yield out
    except BaseException:
        out.discard()
        for c in created:
            shutil.rmtree(c, ignore_errors=True)
        raise
    out.commit()
