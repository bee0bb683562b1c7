"""Atomic output: a run folder holds its earlier run or the complete new one, never a mix.

Every command writes its run folder through :func:`output_directory`, one mechanism
for all of them:

* The run is built in a private staging folder beside the output folder
  (``.NAME.PID-XXXXXXXX.tmp``, on the same file system) and swapped in by two renames
  when the whole run succeeded: the earlier run is moved aside
  (``.NAME.PID-XXXXXXXX.previous.tmp``), the staging folder takes its name, and the
  earlier run is deleted only then.  Ctrl-C and SIGTERM are held back during the swap.
  A failed or interrupted run deletes its staging folder and leaves the earlier run
  exactly as it was; nothing of the earlier run survives a successful one.
* Only a new folder, an empty one or an earlier kalmansfm run (a ``summary.json``
  that kalmansfm wrote, and nothing beside what it lists except reports and hidden
  files) is taken; any other folder is refused.  So is an output folder that is, or
  lies inside, one of the run's inputs, or that holds one of them.
* Staging folders and temporary files left by a killed process (``kill -9``, power
  loss) are swept when the next run into the same place starts; an earlier run left
  aside by a process killed between the two renames is put back.

:func:`atomic_write` writes one file the same way (temporary name, rename) into an
existing folder: a report into its run folder, ``batch_summary.csv``.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import InvalidInputError
from .summary import run_files

__all__ = [
    "OutputDirectory",
    "atomic_write",
    "check_output_directory",
    "last_commit",
    "output_directory",
]

#: Signals held back while a run folder is swapped in (then delivered).
_DEFERRED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: A temporary of this module: ``.NAME.PID-HEX.tmp`` or ``.NAME.PID-HEX.previous.tmp``.
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)-[0-9a-f]{8}(?P<previous>\.previous)?\.tmp$")
#: Without a way to ask whether a process lives (Windows), a temporary is stale after this long.
_STALE_AFTER_S = 24 * 3600


class _CommitLog:
    """How many run folders this process has swapped in, and the last one."""

    count = 0
    last: Path | None = None


def last_commit() -> tuple[int, Path | None]:
    """(number of run folders this process has committed, the last of them).

    The command line compares the count before and after a command to say truthfully,
    after Ctrl-C, whether the new results were written.

    Examples
    --------
    >>> count, _ = last_commit()
    >>> count >= 0
    True
    """
    return _CommitLog.count, _CommitLog.last


def _temporary_name(final: Path, tag: str = "") -> Path:
    return final.with_name(f".{final.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{tag}.tmp")


def _owner_gone(entry: Path, pid: int) -> bool:
    """True when the process that made the temporary ``entry`` no longer runs."""
    if pid == os.getpid():
        return False
    if os.name != "posix":  # os.kill(pid, 0) would terminate the process on Windows
        try:
            return time.time() - entry.lstat().st_mtime > _STALE_AFTER_S
        except OSError:
            return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # it exists but belongs to someone else
        return False
    return False


def _remove(entry: Path) -> None:
    if entry.is_dir() and not entry.is_symlink():
        shutil.rmtree(entry, ignore_errors=True)
    else:
        entry.unlink(missing_ok=True)


def _sweep_stale(final: Path) -> None:
    """Delete the temporaries of ``final`` left by dead processes; put back an earlier run left aside."""
    try:
        siblings = list(final.parent.iterdir())
    except OSError:
        return
    stale = []
    for entry in siblings:
        match = _TEMPORARY.match(entry.name)
        if match is None:
            # a name of an older kalmansfm (``.NAME.HEX.tmp``) has no owner to ask: it is stale
            if entry.name.startswith(f".{final.name}.") and entry.name.endswith(".tmp"):
                stale.append((entry, False))
            continue
        if match["name"] == final.name and _owner_gone(entry, int(match["pid"])):
            stale.append((entry, match["previous"] is not None))
    previous = sorted((e for e, aside in stale if aside), key=lambda e: e.lstat().st_mtime)
    if previous and not final.exists():
        # killed between "earlier run aside" and "new run in": the earlier run is still the result
        os.rename(previous[-1], final)
    for entry, _ in stale:
        if entry.exists():
            _remove(entry)


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` and rename the result to ``path``; remove it on failure.

    An error without a file name (a full disk) is raised naming ``path``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write(d / "a.txt", lambda p: p.write_text("hi")).read_text()
    'hi'
    """
    final = Path(path)
    _sweep_stale(final)
    tmp = _temporary_name(final)
    try:
        write(tmp)
        os.replace(tmp, final)
    except OSError as exc:
        raise _naming(exc, {tmp: final}, final) from None
    finally:
        tmp.unlink(missing_ok=True)
    return final


def _naming(exc: OSError, renames: dict[Path, Path], default: Path) -> OSError:
    """``exc`` naming the file the user will look for: the final name, not a temporary one."""
    name = exc.filename
    if name is None:
        name = default
    else:
        for tmp, final in renames.items():
            text, prefix = os.fspath(name), os.fspath(tmp)
            if text == prefix or text.startswith(prefix + os.sep):
                name = os.fspath(final) + text[len(prefix):]
                break
    return OSError(exc.errno, exc.strerror or str(exc), os.fspath(name))


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM back for the block; deliver them, in order, after it."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread receives signals (and may set handlers)
        return
    received: list[int] = []
    previous = {}
    try:
        for number in _DEFERRED_SIGNALS:
            previous[number] = signal.signal(number, lambda signum, frame: received.append(signum))
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler if handler is not None else signal.SIG_DFL)
    for number in dict.fromkeys(received):
        signal.raise_signal(number)  # runs the restored handler now (KeyboardInterrupt, or the default action)


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _input_root(item: str | os.PathLike[str]) -> Path:
    """The path an input occupies: itself, or for a glob the folder before its first wildcard."""
    parts = Path(item).parts
    plain = parts[: next((k for k, part in enumerate(parts) if any(c in part for c in "*?[")), len(parts))]
    return Path(*plain) if plain else Path(".")


def _check_inputs(folder: Path, inputs: Iterable[str | os.PathLike[str] | None]) -> None:
    resolved = folder.resolve()
    for item in inputs:
        if item is None:
            continue
        root = _input_root(item).resolve()
        if _inside(resolved, root) and root.is_dir():
            where = "is the input" if resolved == root else "lies inside the input"
            raise InvalidInputError(f"output folder {folder} {where} {os.fspath(item)}; choose an output folder outside it")
        if _inside(root, resolved):
            raise InvalidInputError(
                f"the input {os.fspath(item)} lies inside the output folder {folder}, which the run replaces whole; "
                "choose another output folder"
            )


def _check_replaceable(folder: Path) -> None:
    """Refuse an existing folder that is neither empty nor an earlier kalmansfm run with nothing added."""
    resolved = folder.resolve()
    if os.path.ismount(resolved):
        raise InvalidInputError(
            f"output folder {folder} is a mount point, which a run cannot replace; use a folder inside it"
        )
    here = Path.cwd().resolve()
    if _inside(here, resolved):
        raise InvalidInputError(
            f"output folder {folder} is (or holds) the current folder, which a run would replace; "
            "choose an output folder elsewhere"
        )
    # hidden entries (temporaries, .DS_Store) go with the run
    entries = [e for e in folder.iterdir() if not e.name.startswith(".")]
    if not entries:
        return
    owned = run_files(folder)
    if owned is None:
        raise InvalidInputError(
            f"output folder {folder} is not empty and holds no kalmansfm run (no summary.json); "
            "choose a new or empty folder"
        )
    foreign = sorted(e.name for e in entries if e.name not in owned and not (e.is_file() and e.suffix.lower() == ".html"))
    if foreign:
        shown = ", ".join(foreign[:3]) + (" …" if len(foreign) > 3 else "")
        raise InvalidInputError(
            f"output folder {folder} holds {shown}, which its kalmansfm run did not write; a new run replaces the "
            "folder whole: move them away or choose another output folder"
        )


def check_output_directory(
    path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str] | None] = (), whole: bool = True
) -> Path:
    """Raise :class:`InvalidInputError` if ``path`` cannot become a run's output folder; create nothing.

    The folder must be new, empty or an earlier kalmansfm run (see the module notes),
    its parent must be writable, and it must neither be nor lie inside nor hold any of
    ``inputs`` (paths or globs the run reads).  :func:`output_directory` checks this
    itself; call it to check a folder long before the run (``batch``).  With
    ``whole=False`` the folder is a container whose content is kept (the folder of a
    batch's runs): it only has to be a folder that can be created or written in.

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
    >>> check_output_directory(d)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: output folder ... is not empty and holds no kalmansfm run ...
    >>> check_output_directory(d / "run", inputs=[d])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: output folder ... lies inside the input ...; choose an output folder outside it
    """
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise InvalidInputError(f"output folder {folder} exists and is not a folder")
    existing = next((p for p in folder.absolute().parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InvalidInputError(f"output folder {folder} is not writable ({existing} is a file, not a folder)")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidInputError(f"output folder {folder} is not writable (no write permission in {existing})")
    if not whole:
        if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
            raise InvalidInputError(f"output folder {folder} is not writable (no write permission)")
        return folder
    _check_inputs(folder, inputs)
    if folder.is_dir():
        _check_replaceable(folder)
    return folder


class OutputDirectory:
    """The run being built: files go to :attr:`staging` and appear in :attr:`path` together at commit.

    Attributes
    ----------
    path : the run folder as the user named it.
    staging : the private folder the run is built in until it is swapped in.
    """

    def __init__(self, path: Path, staging: Path) -> None:
        self.path = path
        self.staging = staging
        self.last_file: str | None = None
        self.committed = False

    def file(self, name: str) -> Path:
        """The path to write ``name`` (relative, ``/``-separated) to; it becomes ``path / name`` at commit."""
        target = self.staging / name
        target.parent.mkdir(parents=True, exist_ok=True)
        self.last_file = name
        return target

    def write_text(self, name: str, text: str) -> Path:
        """Stage a text file; returns its final path."""
        self.file(name).write_text(text, encoding="utf-8")
        return self.path / name

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Stage a binary file; returns its final path."""
        self.file(name).write_bytes(data)
        return self.path / name

    def commit(self) -> None:
        """Swap the staged run in for the folder's earlier content (Ctrl-C and SIGTERM wait for it)."""
        previous = None
        swapped = False
        try:
            with _signals_deferred():
                if self.path.exists():
                    previous = _temporary_name(self.path, ".previous")
                    os.rename(self.path, previous)
                try:
                    os.rename(self.staging, self.path)
                except BaseException:
                    if previous is not None:
                        os.rename(previous, self.path)
                    raise
                swapped = self.committed = True
                _CommitLog.count += 1
                _CommitLog.last = self.path
        finally:
            if swapped and previous is not None:
                shutil.rmtree(previous, ignore_errors=True)


@contextmanager
def output_directory(
    path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str] | None] = ()
) -> Iterator[OutputDirectory]:
    """Context manager that owns a run's output folder: build the run inside, it appears whole at the end.

    On entry the folder is checked (:func:`check_output_directory`, with the run's
    ``inputs``) and a staging folder is made beside it; files staged through the yielded
    :class:`OutputDirectory` replace the folder's earlier content together when the block
    succeeds.  On an exception (Ctrl-C included) the staging folder and any parent folder
    this call created are removed, the earlier run is untouched, and the exception
    propagates; an ``OSError`` without a file name (a full disk) is raised naming the
    file that was being written.  Enter it before the work, so that a bad ``--out`` is
    reported at once.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> with output_directory(d) as out:
    ...     _ = out.write_text("result.csv", "a,b\\n1,2\\n")
    ...     _ = out.write_text("summary.json", '{"command": "example", "schema_version": 0}')
    >>> sorted(p.name for p in d.iterdir())
    ['result.csv', 'summary.json']
    >>> with output_directory(d) as out:  # a rerun replaces the earlier run whole
    ...     _ = out.write_text("other.csv", "c\\n3\\n")
    >>> sorted(p.name for p in d.iterdir())
    ['other.csv']
    """
    _sweep_stale(Path(path))
    folder = check_output_directory(path, inputs=inputs)
    created = [p for p in folder.absolute().parents if not p.exists()]
    try:
        folder.absolute().parent.mkdir(parents=True, exist_ok=True)
        staging = _temporary_name(folder)
        staging.mkdir()
    except OSError as exc:
        for c in created:
            shutil.rmtree(c, ignore_errors=True)
        raise InvalidInputError(f"output folder {folder} is not writable ({exc.strerror or exc})") from None
    out = OutputDirectory(folder, staging)
    try:
        yield out
        out.commit()
    except OSError as exc:
        last = folder / out.last_file if out.last_file else folder
        raise _naming(exc, {staging: folder}, last) from None
    finally:
        if not out.committed:
            shutil.rmtree(staging, ignore_errors=True)
            for c in created:
                shutil.rmtree(c, ignore_errors=True)
