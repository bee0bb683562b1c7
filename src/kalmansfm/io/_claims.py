"""Temporaries that can prove they are ours, and the sweep of those whose owner is gone.

A run builds its folder, and :func:`kalmansfm.io.atomic_write` its file, under a temporary
name beside the final one.  Before creating one, the process writes an *owner marker*
beside it, with the same stem::

    .NAME.PID-TOKEN.owner          {"kalmansfm": "temporary", "name": NAME, "pid": PID, "host": HOST, "token": TOKEN}
    .NAME.PID-TOKEN.tmp            the staging folder, or the temporary file
    .NAME.PID-TOKEN.previous.tmp   the earlier run, moved aside during the swap

TOKEN is 16 random hex digits.  A temporary is removed by anyone but its owner only when its
marker is a regular file whose content repeats the name, process id and token of its file
name, was written on this host, and that process no longer runs.  A file that merely looks
like a temporary (``.out.backup.tmp``, ``.out.12345.tmp``, a marker with other content, one
from another host) is never touched.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Claim", "claim", "release", "sweep", "temporary_state"]

_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)-(?P<token>[0-9a-f]{16})(?P<kind>\.tmp|\.previous\.tmp|\.owner)$")
_MARKER_BYTES = 4096
#: Without a way to ask whether a process lives (Windows), a temporary is stale after this long.
_STALE_AFTER_S = 24 * 3600


@dataclass(frozen=True)
class Claim:
    """The temporaries of one process for one final name (see the module notes)."""

    final: Path
    pid: int
    token: str

    def _sibling(self, suffix: str) -> Path:
        return self.final.with_name(f".{self.final.name}.{self.pid}-{self.token}{suffix}")

    @property
    def marker(self) -> Path:
        """The owner marker."""
        return self._sibling(".owner")

    @property
    def temporary(self) -> Path:
        """The staging folder or temporary file."""
        return self._sibling(".tmp")

    @property
    def aside(self) -> Path:
        """Where the earlier run waits during the swap."""
        return self._sibling(".previous.tmp")

    def record(self) -> dict[str, object]:
        """What the marker holds."""
        return {"kalmansfm": "temporary", "name": self.final.name, "pid": self.pid, "host": socket.gethostname(),
                "token": self.token}


def claim(final: Path) -> Claim:
    """Write the owner marker of a new temporary for ``final``; create the temporary itself after this.

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> c = claim(d / "run")
    >>> c.marker.exists(), c.temporary.name.startswith(".run."), temporary_state(d, c.marker.name)
    (True, True, 'live')
    >>> release(c); sorted(d.iterdir())
    []
    """
    made = Claim(final, os.getpid(), secrets.token_hex(8))
    descriptor = os.open(made.marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        os.write(descriptor, json.dumps(made.record()).encode())
    except BaseException:
        os.close(descriptor)
        os.unlink(made.marker)
        raise
    os.close(descriptor)
    return made


def _remove(entry: Path) -> None:
    if entry.is_dir() and not entry.is_symlink():
        shutil.rmtree(entry, ignore_errors=True)
    else:
        try:
            entry.unlink()
        except FileNotFoundError:
            pass


def release(made: Claim, *, aside: bool = True) -> None:
    """Remove the temporaries of ``made`` (the earlier run aside too, when ``aside``), the marker last."""
    _remove(made.temporary)
    if aside:
        _remove(made.aside)
    try:
        made.marker.unlink()
    except FileNotFoundError:
        pass


def _process_gone(pid: int, marker: Path) -> bool:
    if pid == os.getpid():
        return False
    if os.name != "posix":  # os.kill(pid, 0) would terminate the process on Windows
        try:
            return time.time() - marker.lstat().st_mtime > _STALE_AFTER_S
        except OSError:
            return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # it exists but belongs to someone else
        return False
    return False


def _proven(folder: Path, name: str) -> Claim | None:
    """The claim that ``folder / name`` belongs to, when its marker proves it; else None."""
    match = _NAME.match(name)
    if match is None:
        return None
    made = Claim(folder / match["name"], int(match["pid"]), match["token"])
    try:
        if not made.marker.is_file() or made.marker.is_symlink() or made.marker.stat().st_size > _MARKER_BYTES:
            return None
        record = json.loads(made.marker.read_bytes())
    except (OSError, ValueError):
        return None
    return made if record == made.record() else None


def temporary_state(folder: Path, name: str) -> str | None:
    """``'live'`` or ``'dead'`` for a proven temporary (or marker) ``folder / name`` of kalmansfm; None otherwise."""
    made = _proven(folder, name)
    if made is None:
        return None
    return "dead" if _process_gone(made.pid, made.marker) else "live"


def sweep(final: Path) -> bool:
    """Remove the proven temporaries of ``final`` whose process is gone; put back an earlier run left aside.

    Returns True when an earlier run was put back (killed between the two renames of a swap).
    """
    try:
        names = sorted(os.listdir(final.parent))
    except OSError:
        return False
    restored = False
    for name in names:
        if not name.endswith(".owner"):
            continue
        made = _proven(final.parent, name)
        if made is None or made.final.name != final.name or not _process_gone(made.pid, made.marker):
            continue
        aside = made.aside
        if aside.is_dir() and not aside.is_symlink() and not os.path.lexists(final):
            try:
                os.rename(aside, final)
            except OSError:
                continue  # left as it is, marker included, for the next run to try again
            restored = True
        release(made)
    return restored
