"""Many sequences at once: each one tracked and reconstructed as an independent Dask task.

:func:`run_batch` submits one :func:`kalmansfm.pipeline.run_demo` call per
sequence to a ``dask.distributed`` cluster (a local one by default, or an
existing scheduler), collects a row of results per sequence, and never lets a
failing sequence stop the others.  A sequence whose run folder already holds a
``summary.json`` is skipped, so an interrupted batch can simply be run again.
"""

from __future__ import annotations

import csv
import io
import logging
import re
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from ..errors import InvalidInputError, KalmanSfmError
from ..io.atomic import atomic_write, check_output_directory
from ..io.frames import read_frames
from ..io.summary import SUMMARY_FILE, RunSummary, read_summary
from .cluster import check_workers, dask_client
from .demo import run_demo

__all__ = ["BatchRow", "BatchResult", "check_sequence", "run_batch", "SCENE_PREFIX"]

log = logging.getLogger("kalmansfm")

#: ``scene:SEED`` names the built-in scene rendered with that seed instead of a path.
SCENE_PREFIX = "scene:"
BATCH_SUMMARY_FILE = "batch_summary.csv"


@dataclass(frozen=True)
class BatchRow:
    """The outcome of one sequence: ``status`` is ``ok``, ``skipped`` (already done) or ``failed``."""

    sequence: str
    output: str
    status: str
    frames: int | None = None
    tracks: int | None = None
    fraction_tracked: float | None = None
    residual_rms_px: float | None = None
    seconds: float | None = None
    error: str | None = None


@dataclass(frozen=True)
class BatchResult:
    """All rows, in the order the sequences were given, and the summary file written."""

    rows: tuple[BatchRow, ...]
    summary_path: Path

    @property
    def failed(self) -> tuple[BatchRow, ...]:
        """The rows whose sequence failed."""
        return tuple(r for r in self.rows if r.status == "failed")

    def table(self) -> str:
        """An aligned text table of the rows."""
        header = ["sequence", "status", "frames", "tracks", "tracked", "residual px", "seconds", "error"]
        body = [
            [
                r.sequence,
                r.status,
                "" if r.frames is None else str(r.frames),
                "" if r.tracks is None else str(r.tracks),
                "" if r.fraction_tracked is None else f"{r.fraction_tracked:.1%}",
                "" if r.residual_rms_px is None else f"{r.residual_rms_px:.3f}",
                "" if r.seconds is None else f"{r.seconds:.1f}",
                r.error or "",
            ]
            for r in self.rows
        ]
        widths = [max(len(h), *(len(row[i]) for row in body)) for i, h in enumerate(header)]
        lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
        lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in body]
        return "\n".join(lines)


def _folder_names(sequences: Sequence[str]) -> list[str]:
    """One distinct, filesystem-safe folder name per sequence."""
    names: list[str] = []
    for spec in sequences:
        base = spec.replace(SCENE_PREFIX, "scene-", 1) if spec.startswith(SCENE_PREFIX) else Path(spec).stem or "seq"
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", base).strip("._") or "seq"
        name, k = base, 2
        while name in names:
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def _parse(spec: str) -> dict[str, Any]:
    if spec.startswith(SCENE_PREFIX):
        seed = spec[len(SCENE_PREFIX):]
        if not seed.isdigit():
            raise InvalidInputError(f"sequence {spec!r}: the built-in scene is named scene:SEED with an integer seed")
        return {"input": None, "seed": int(seed)}
    if not (Path(spec).exists() or any(ch in spec for ch in "*?[")):
        raise InvalidInputError(f"sequence {spec!r} does not exist")
    return {"input": spec}


def check_sequence(spec: str) -> None:
    """Raise :class:`InvalidInputError` if ``spec`` is visibly not a sequence (before any work).

    ``scene:SEED`` needs an integer seed; a path must exist and hold enough frames
    (the checks :func:`kalmansfm.io.read_frames` makes without decoding them all).

    Examples
    --------
    >>> check_sequence("scene:3")
    >>> check_sequence("scene:x")
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: sequence 'scene:x': the built-in scene is named scene:SEED with an integer seed
    """
    if _parse(spec)["input"] is not None:
        read_frames(spec)


def _row_from_summary(spec: str, out_dir: str, status: str, summary: RunSummary, seconds: float | None) -> BatchRow:
    t, f = summary.tracking, summary.structure
    return BatchRow(
        spec,
        out_dir,
        status,
        frames=None if t is None else t.frames,
        tracks=None if t is None else t.tracks,
        fraction_tracked=None if t is None else t.measured_fraction,
        residual_rms_px=None if f is None else f.residual_rms_px,
        seconds=seconds,
        error=summary.structure_error,
    )


def _finished_row(spec: str, folder: Path) -> BatchRow | None:
    """The row of an earlier, finished run of this sequence, or None if there is none."""
    try:
        summary = read_summary(folder / SUMMARY_FILE)
    except InvalidInputError:
        return None
    return _row_from_summary(spec, str(folder), "skipped", summary, None)


def process_sequence(spec: str, out_dir: str, options: dict[str, Any]) -> BatchRow:
    """Run the pipeline on one sequence and return its row; errors become a ``failed`` row.

    This is the function each Dask task runs; it is also usable on its own.
    """
    started = time.perf_counter()
    try:
        result = run_demo(out_dir, command="batch", **_parse(spec), **options)
    except (KalmanSfmError, OSError) as exc:
        return BatchRow(spec, out_dir, "failed", seconds=time.perf_counter() - started, error=str(exc))
    except Exception as exc:  # one broken sequence must not stop the batch
        return BatchRow(
            spec, out_dir, "failed", seconds=time.perf_counter() - started, error=f"{type(exc).__name__}: {exc}"
        )
    return _row_from_summary(spec, out_dir, "ok", result.summary, time.perf_counter() - started)


def run_batch(
    sequences: Sequence[str],
    out_dir: str | Path,
    *,
    scheduler: str | None = None,
    n_workers: int | None = None,
    html: bool = False,
    progress: bool = False,
    **pipeline_options: Any,
) -> BatchResult:
    """Track and reconstruct every sequence as an independent task on Dask.

    Parameters
    ----------
    sequences : paths (image folders, globs, videos) or ``scene:SEED`` for the built-in scene.
    out_dir : one run folder per sequence is created inside, plus ``batch_summary.csv``.
    scheduler : address of an existing ``dask.distributed`` scheduler; None starts a
        local cluster of ``n_workers`` single-threaded worker processes.
    n_workers : local workers (default: the number of CPU cores).
    html : build each run's report.html.
    progress : a progress bar over sequences on stderr.
    **pipeline_options : more keyword arguments of :func:`~kalmansfm.pipeline.run_demo`.

    Returns
    -------
    BatchResult
        One row per sequence; failed sequences are rows with ``status == "failed"``.
    """
    if not sequences:
        raise InvalidInputError("give at least one sequence")
    check_workers(n_workers)
    root = check_output_directory(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    names = _folder_names(list(sequences))
    options = {"html": html, **pipeline_options}

    rows: dict[int, BatchRow] = {}
    todo = []
    for k, (spec, name) in enumerate(zip(sequences, names)):
        folder = root / name
        finished = _finished_row(spec, folder)
        if finished is not None:
            rows[k] = finished
        else:
            todo.append((k, spec, str(folder)))

    if todo:
        from dask.distributed import as_completed

        with dask_client(scheduler, n_workers) as client:
            futures = {
                client.submit(process_sequence, spec, folder, options, key=f"kalmansfm-{k}-{name}", pure=False): k
                for (k, spec, folder), name in zip(todo, [names[k] for k, _, _ in todo])
            }
            iterator = as_completed(futures)
            if progress:
                from tqdm import tqdm

                iterator = tqdm(iterator, total=len(futures), unit="sequence", desc="batch", leave=False)
            for future in iterator:
                k = futures[future]
                try:
                    rows[k] = future.result()
                except Exception as exc:  # a worker died: the sequence failed, the batch goes on
                    rows[k] = BatchRow(sequences[k], str(root / names[k]), "failed", error=f"{type(exc).__name__}: {exc}")

    ordered = tuple(rows[k] for k in range(len(sequences)))
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(asdict(ordered[0]).keys()), lineterminator="\n")
    writer.writeheader()
    for row in ordered:
        writer.writerow({k: "" if v is None else v for k, v in asdict(row).items()})
    summary_path = atomic_write(root / BATCH_SUMMARY_FILE, lambda p: p.write_text(buffer.getvalue(), encoding="utf-8"))
    return BatchResult(ordered, summary_path)
