"""Atomic output: a run folder holds its earlier run or the complete new one, never a mix.

Every command writes its run folder through :func:`output_directory`, one mechanism
for all of them:

* The run is built in a private staging folder beside the output folder
  (``.NAME.PID-TOKEN.tmp``, on the same file system, with an owner marker
  ``.NAME.PID-TOKEN.owner`` beside it) and swapped in by two renames when the whole run
  succeeded: the earlier run is moved aside (``.NAME.PID-TOKEN.previous.tmp``), the
  staging folder takes its name, and the earlier run is deleted only then.  Ctrl-C and
  SIGTERM are held back during the swap.  A failed or interrupted run deletes its staging
  folder and leaves the earlier run exactly as it was; nothing of the earlier run
  survives a successful one.  Parent folders the run created are removed again only while
  they are empty: another run may have written into them meanwhile.
* Only a new folder, an empty one or an earlier kalmansfm run is taken.  A run owns exactly
  the files its ``summary.json`` lists, its HTML reports and the proven temporaries of
  finished processes; any other file, hidden ones included (``.git``), makes the folder
  someone else's, and it is refused.  Only the litter operating systems leave
  (``.DS_Store``, ``Thumbs.db``, ``desktop.ini``) counts as nothing.  The ownership is
  checked before the work and again, on the earlier run moved aside, at the swap.  An
  output folder that is, or lies inside, one of the run's inputs, holds one of them, or
  holds the current folder is refused before anything changes.
* Temporaries left by a killed process (``kill -9``, power loss) are swept when the next
  run into the same place starts, but only those whose owner marker proves they are ours
  and whose process no longer runs (:mod:`kalmansfm.io._claims`); an earlier run left aside
  by a process killed between the two renames is put back.
* A symbolic link given as the output folder stays a link: the run replaces the folder it
  points to.
* When the folder held a run of another command or input, the swap logs one line saying what
  was replaced (command, input, date).

:func:`atomic_write` writes one file the same way (temporary name, rename) into an
existing folder: a report into its run folder, ``batch_summary.csv``.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import signal
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import ClassVar

from ..errors import InvalidInputError
from ._claims import Claim, claim, release, sweep, temporary_state
from .paths import resolved

__all__ = [
    "OutputDirectory",
    "atomic_write",
    "check_output_directory",
    "last_commit",
    "output_directory",
]

log = logging.getLogger("kalmansfm")

#: Signals held back while a run folder is swapped in (then delivered).
_DEFERRED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Files an operating system leaves in any folder it shows; they hold nothing of the user's.
_LITTER = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
_SUMMARY = "summary.json"
#: How a report of kalmansfm begins (kalmansfm.report.html.render_report); read from its first bytes.
_REPORT_START, _REPORT_TITLE, _REPORT_HEAD_BYTES = b"<!DOCTYPE html>", b"<h1>kalmansfm report</h1>", 16384
#: Attempts at a swap when another run into the same folder swaps at the same moment.
_SWAP_ATTEMPTS = 3


class _CommitLog:
    """How many results this process has put in place (run folders swapped in, files written), and the last one."""

    count = 0
    last: Path | None = None
    #: Staging folders being built now: a file written into one is not a result yet.
    building: ClassVar[set[Path]] = set()


def last_commit() -> tuple[int, Path | None]:
    """(number of results this process has put in place, the last of them).

    A result is a run folder swapped in by :func:`output_directory` or a file written by
    :func:`atomic_write` outside a staging folder (a report into its run folder).  The command
    line compares the count before and after a command to say truthfully, after Ctrl-C or a
    failure to print, whether the new results were written.

    Examples
    --------
    >>> count, _ = last_commit()
    >>> count >= 0
    True
    """
    return _CommitLog.count, _CommitLog.last


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` and rename the result to ``path``; remove it on failure.

    An error without a file name (a full disk) is raised naming ``path``.  Proven
    temporaries of ``path`` left by finished processes are removed first.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write(d / "a.txt", lambda p: p.write_text("hi")).read_text()
    'hi'
    >>> sorted(p.name for p in d.iterdir())
    ['a.txt']
    """
    final = Path(path)
    sweep(final)
    made = None
    try:
        with _signals_deferred():  # the marker is either not made or known to the clean-up below
            made = claim(final)
        write(made.temporary)
        os.replace(made.temporary, final)
        if Path(os.path.abspath(final.parent)) not in _CommitLog.building:
            _CommitLog.count += 1
            _CommitLog.last = final
    except OSError as exc:
        raise _naming(exc, {} if made is None else {made.temporary: final}, final) from None
    finally:
        if made is not None:
            release(made)
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


def _check_inputs(folder: Path, target: Path, inputs: Iterable[str | os.PathLike[str] | None]) -> None:
    for item in inputs:
        if item is None:
            continue
        root = resolved(_input_root(item))
        if _inside(target, root) and root.is_dir():
            where = "is the input" if target == root else "lies inside the input"
            raise InvalidInputError(f"output folder {folder} {where} {os.fspath(item)}; choose an output folder outside it")
        if _inside(root, target):
            raise InvalidInputError(
                f"the input {os.fspath(item)} lies inside the output folder {folder}, which the run replaces whole; "
                "choose another output folder"
            )


def _target(folder: Path) -> Path:
    """The folder a run replaces: ``folder`` itself, or the folder a symbolic link ``folder`` points to."""
    if not folder.is_symlink():
        return Path(os.path.abspath(folder))
    target = resolved(folder)
    if not target.exists():
        raise InvalidInputError(f"output folder {folder} is a symbolic link to {target}, which does not exist")
    return target


def _is_litter(entry: Path) -> bool:
    return entry.name in _LITTER and entry.is_file() and not entry.is_symlink()


def _is_our_report(entry: Path) -> bool:
    """A report kalmansfm wrote (report.html or another ``report --name``), known by how it begins."""
    if entry.suffix.lower() != ".html" or entry.is_symlink() or not entry.is_file():
        return False
    try:
        with entry.open("rb") as handle:
            head = handle.read(_REPORT_HEAD_BYTES)
    except OSError:
        return False
    return head.startswith(_REPORT_START) and _REPORT_TITLE in head


def _summary_record(folder: Path) -> dict | None:
    """The parsed ``summary.json`` of ``folder`` when kalmansfm wrote it (a regular file with command and schema)."""
    path = folder / _SUMMARY
    if path.is_symlink() or not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not (isinstance(data, dict) and isinstance(data.get("command"), str) and "schema_version" in data):
        return None
    return data


def _listed_files(record: dict) -> frozenset[str]:
    """The relative paths a summary lists (itself included); names that could leave the folder are ignored."""
    listed = {_SUMMARY}
    names = record.get("files")
    for name in names if isinstance(names, list) else ():
        if not isinstance(name, str) or "\\" in name or "\x00" in name:
            continue
        parts = PurePosixPath(name).parts
        if parts and not PurePosixPath(name).is_absolute() and not {"", ".", ".."} & set(parts):
            listed.add("/".join(parts))
    return frozenset(listed)


def _not_ours(folder: Path, listed: frozenset[str]) -> list[str]:
    """Every file or empty folder below ``folder`` that the run did not write (relative names, sorted)."""
    split = [PurePosixPath(name).parts for name in listed]
    prefixes = {"/".join(parts[:k]) for parts in split for k in range(1, len(parts))}  # the folders of listed files
    foreign = []
    for top, dirs, files in os.walk(folder):
        here = Path(top)
        relative_top = here.relative_to(folder).as_posix()
        prefix = "" if relative_top == "." else relative_top + "/"
        for name in dirs + files:
            entry = here / name
            relative = prefix + name
            if entry.is_dir() and not entry.is_symlink():
                if relative not in prefixes and not any(os.scandir(entry)):
                    foreign.append(relative + "/")
                continue
            ours = (
                (relative in listed and entry.is_file() and not entry.is_symlink())
                or (not prefix and _is_our_report(entry))
                or _is_litter(entry)
                or temporary_state(here, name) == "dead"
            )
            if not ours:
                foreign.append(relative)
    return sorted(foreign)


def _ownership_problem(folder: Path, shown: Path) -> str | None:
    """Why the existing folder ``folder`` (named ``shown``) may not be replaced by a run, or None."""
    names = sorted(os.listdir(folder))
    live = [name for name in names if temporary_state(folder, name) == "live"]
    if live:
        return (f"output folder {shown} is being written by another kalmansfm process ({live[0]}); "
                "wait for it to finish or choose another output folder")
    content = [name for name in names if not _is_litter(folder / name) and temporary_state(folder, name) is None]
    if not content:
        return None
    record = _summary_record(folder)
    if record is None:
        return (f"output folder {shown} is not empty and holds no kalmansfm run (no summary.json); "
                "choose a new or empty folder")
    foreign = _not_ours(folder, _listed_files(record))
    if foreign:
        shown_names = ", ".join(foreign[:3]) + (" …" if len(foreign) > 3 else "")
        return (f"output folder {shown} holds {shown_names}, which its kalmansfm run did not write; a new run "
                "replaces the folder whole: move them away or choose another output folder")
    return None


def _check_replaceable(folder: Path, target: Path) -> None:
    """Refuse an existing folder that is neither empty nor an earlier kalmansfm run with nothing added."""
    real = resolved(target)
    if os.path.ismount(real):
        raise InvalidInputError(
            f"output folder {folder} is a mount point, which a run cannot replace; use a folder inside it"
        )
    if _inside(resolved(Path.cwd()), real):
        raise InvalidInputError(
            f"output folder {folder} is (or holds) the current folder, which a run would replace; "
            "choose an output folder elsewhere"
        )
    try:
        problem = _ownership_problem(target, folder)
    except OSError as exc:
        raise InvalidInputError(f"output folder {folder} cannot be read ({exc.strerror or exc})") from None
    if problem is not None:
        raise InvalidInputError(problem)


def check_output_directory(
    path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str] | None] = (), whole: bool = True
) -> Path:
    """Raise :class:`InvalidInputError` if ``path`` cannot become a run's output folder; create nothing.

    The folder must be new, empty or an earlier kalmansfm run (see the module notes),
    its parent must be writable, and it must neither be nor lie inside nor hold any of
    ``inputs`` (paths or globs the run reads), nor hold the current folder.
    :func:`output_directory` checks this itself; call it to check a folder long before
    the run (``batch``).  With ``whole=False`` the folder is a container whose content is
    kept (the folder of a batch's runs): it only has to be a folder that can be created
    or written in.

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
    target = _target(folder)
    if target.exists() and not target.is_dir():
        raise InvalidInputError(f"output folder {folder} exists and is not a folder")
    existing = next((p for p in target.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InvalidInputError(f"output folder {folder} is not writable ({existing} is a file, not a folder)")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidInputError(f"output folder {folder} is not writable (no write permission in {existing})")
    if not whole:
        if target.is_dir() and not os.access(target, os.W_OK | os.X_OK):
            raise InvalidInputError(f"output folder {folder} is not writable (no write permission)")
        return folder
    _check_inputs(folder, resolved(target), inputs)
    if target.is_dir():
        _check_replaceable(folder, target)
    return folder


def _run_identity(folder: Path) -> tuple[str, str, str, str] | None:
    """(command, what the input resolves to, the input as shown, date) of the run in ``folder``, or None."""
    record = _summary_record(folder)
    if record is None:
        return None
    source = record.get("source")
    shown = str(record.get("input", "?"))
    key = source.get("input") if isinstance(source, dict) and isinstance(source.get("input"), str) else shown
    return record["command"], key, shown, str(record.get("created", "an unknown date"))


class OutputDirectory:
    """The run being built: files go to :attr:`staging` and appear in :attr:`path` together at commit.

    Attributes
    ----------
    path : the run folder as the user named it.
    staging : the private folder the run is built in until it is swapped in.
    """

    def __init__(self, path: Path, staging: Path, target: Path, owner: Claim) -> None:
        self.path = path
        self.staging = staging
        self.last_file: str | None = None
        self.committed = False
        self._target = target  # the folder replaced: path, or the folder a link path points to
        self._claim = owner

    def file(self, name: str) -> Path:
        """The path to write ``name`` (relative, ``/``-separated) to; it becomes ``path / name`` at commit."""
        target = self.staging / name
        target.parent.mkdir(parents=True, exist_ok=True)
        self.last_file = name
        return target

    def write_text(self, name: str, text: str) -> Path:
        """Stage a UTF-8 text file; returns its final path.

        A file name in ``text`` that is not UTF-8 is written as ``\\udcff`` escapes.
        """
        self.file(name).write_text(text, encoding="utf-8", errors="backslashreplace")
        return self.path / name

    def write_chunks(self, name: str, chunks: Iterable[str]) -> Path:
        """Stage a UTF-8 text file from pieces written as they come (a large table never held whole)."""
        with open(self.file(name), "w", encoding="utf-8", errors="backslashreplace") as handle:
            for chunk in chunks:
                handle.write(chunk)
        return self.path / name

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Stage a binary file; returns its final path."""
        self.file(name).write_bytes(data)
        return self.path / name

    def commit(self) -> None:
        """Swap the staged run in for the folder's earlier content (Ctrl-C and SIGTERM wait for it).

        The earlier content is moved aside first and its ownership checked again: a file that
        appeared in it during the run puts it back and raises :class:`InvalidInputError`.
        """
        aside = self._claim.aside
        replaced = None
        try:
            with _signals_deferred():
                for attempt in range(_SWAP_ATTEMPTS):
                    moved = self._move_earlier_aside(aside)
                    if moved:
                        replaced = _run_identity(aside)
                    try:
                        os.rename(self.staging, self._target)
                    except OSError as exc:
                        if moved:
                            self._put_back(aside)
                        # another run swapped its folder in at this moment: take its place as a rerun would
                        if exc.errno in (errno.EEXIST, errno.ENOTEMPTY) and attempt + 1 < _SWAP_ATTEMPTS:
                            continue
                        raise
                    self.committed = True
                    _CommitLog.count += 1
                    _CommitLog.last = self.path
                    break
        finally:
            if self.committed and os.path.lexists(aside):
                shutil.rmtree(aside, ignore_errors=True)
        if self.committed and replaced is not None:
            self._say_what_was_replaced(replaced)

    def _move_earlier_aside(self, aside: Path) -> bool:
        """Move the folder's earlier content aside; False when there is none. Refuse it if it is not ours."""
        if not os.path.lexists(self._target):
            return False
        try:
            os.rename(self._target, aside)
        except FileNotFoundError:  # another run's swap moved it away this instant
            return False
        try:
            problem = _ownership_problem(aside, self.path)
        except OSError as exc:
            problem = f"output folder {self.path} cannot be read ({exc.strerror or exc})"
        if problem is not None:
            self._put_back(aside)
            raise InvalidInputError(f"{problem} (it changed while this run worked; the new results were not written)")
        return True

    def _put_back(self, aside: Path) -> None:
        """Return the earlier content to its place; if another run took the place meanwhile, keep it visibly apart."""
        try:
            os.rename(aside, self._target)
            return
        except OSError:
            pass
        if _ownership_problem(aside, self.path) is None:
            shutil.rmtree(aside, ignore_errors=True)  # a complete run of ours, superseded by the other run's
            return
        kept = self._target.with_name(f"{self._target.name}.kept-{aside.name.rsplit('-', 1)[-1][:8]}")
        os.rename(aside, kept)
        raise InvalidInputError(f"output folder {self.path} was replaced by another run while this one worked; its "
                                f"earlier content, with files kalmansfm did not write, is in {kept}")

    def _say_what_was_replaced(self, earlier: tuple[str, str, str, str]) -> None:
        now = _run_identity(self._target)
        if now is None or now[:2] == earlier[:2]:
            return
        command, _, shown, created = earlier
        log.warning("replaced %s: it held a %s run of %s made %s", self.path, command, shown, created)


def _remove_created(created: list[Path]) -> None:
    """Remove the parent folders a run created, deepest first, while they are empty."""
    for folder in created:
        try:
            os.rmdir(folder)
        except OSError:
            return  # something else is in it now (another run's folder): it stays, and so do its parents


def _start(folder: Path, target: Path) -> tuple[Claim, list[Path]]:
    """Create the missing parent folders, the owner marker and the staging folder; (claim, parents created)."""
    for attempt in range(_SWAP_ATTEMPTS):
        created = [p for p in target.parents if not p.exists()]
        made = None
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            made = claim(target)
            made.temporary.mkdir()
            return made, created
        except FileNotFoundError:  # a parent was removed by another run's clean-up at this instant
            if made is not None:
                release(made)
            if attempt + 1 < _SWAP_ATTEMPTS:
                continue
            raise InvalidInputError(
                f"output folder {folder} is not writable (its parent folder keeps vanishing)") from None
        except OSError as exc:
            if made is not None:
                release(made)
            _remove_created(created)
            raise InvalidInputError(f"output folder {folder} is not writable ({exc.strerror or exc})") from None
    raise AssertionError("unreachable")


@contextmanager
def output_directory(
    path: str | os.PathLike[str], *, inputs: Iterable[str | os.PathLike[str] | None] = ()
) -> Iterator[OutputDirectory]:
    """Context manager that owns a run's output folder: build the run inside, it appears whole at the end.

    On entry the folder is checked (:func:`check_output_directory`, with the run's
    ``inputs``), proven temporaries of finished runs beside it are swept, and a staging
    folder is made beside it; files staged through the yielded :class:`OutputDirectory`
    replace the folder's earlier content together when the block succeeds.  On an
    exception (Ctrl-C included) the staging folder and the parent folders this call
    created (while they are still empty) are removed, the earlier run is untouched, and
    the exception propagates; an ``OSError`` without a file name (a full disk) is raised
    naming the file that was being written.  Enter it before the work, so that a bad
    ``--out`` is reported at once.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp()) / "run"
    >>> with output_directory(d) as out:
    ...     _ = out.write_text("result.csv", "a,b\\n1,2\\n")
    ...     _ = out.write_text("summary.json", '{"command": "example", "schema_version": 0, '
    ...                                        '"files": ["result.csv", "summary.json"]}')
    >>> sorted(p.name for p in d.iterdir())
    ['result.csv', 'summary.json']
    >>> with output_directory(d) as out:  # a rerun replaces the earlier run whole
    ...     _ = out.write_text("other.csv", "c\\n3\\n")
    >>> sorted(p.name for p in d.iterdir())
    ['other.csv']
    """
    folder = check_output_directory(path, inputs=inputs)  # before anything changes
    target = _target(folder)
    if sweep(target):  # an earlier run put back: it is checked like any other
        check_output_directory(path, inputs=inputs)
    made: Claim | None = None
    created: list[Path] = []
    out: OutputDirectory | None = None
    try:
        # a Ctrl-C while the marker and the staging folder are made waits until the clean-up below knows them
        with _signals_deferred():
            made, created = _start(folder, target)
            out = OutputDirectory(folder, made.temporary, target, made)
            _CommitLog.building.add(Path(os.path.abspath(made.temporary)))
        yield out
        out.commit()
    except OSError as exc:
        last = folder / out.last_file if out is not None and out.last_file else folder
        raise _naming(exc, {} if made is None else {made.temporary: folder}, last) from None
    finally:
        if made is not None:
            _CommitLog.building.discard(Path(os.path.abspath(made.temporary)))
            release(made, aside=False)  # the swap has removed the earlier run, or put it back
        if out is None or not out.committed:
            _remove_created(created)
