"""Many sequences at once: each one tracked and reconstructed as an independent Dask task.

:func:`run_batch` checks every sequence first and reports each one that cannot run as a
``failed`` row; it submits one :func:`kalmansfm.pipeline.run_demo` call per remaining
sequence to a ``dask.distributed`` cluster (a local one by default, or an existing
scheduler), collects a row of results per sequence, and never lets a failing sequence
stop the others.  Each sequence has its own run folder, named after the input and a
digest of its resolved path (stable from one batch to the next, distinct for
``a/images`` and ``b/images``).  A sequence whose folder holds a finished run made from
the same input files with the same options (:class:`~kalmansfm.io.summary.RunSource`)
is ``skipped``, so an interrupted batch can simply be run again; any other earlier run
there is replaced.
"""

from __future__ import annotations

import csv
import hashlib
import io
import logging
import os
import re
import signal
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from ..errors import Interrupted, InvalidInputError, KalmanSfmError
from ..io._csv import number
from ..io.atomic import atomic_write, check_output_directory
from ..io.frames import read_frames
from ..io.summary import SUMMARY_FILE, RunSource, RunSummary, read_summary
from .cluster import check_cluster, dask_client
from .demo import demo_source, run_demo
from .requests import DemoRequest

__all__ = ["BatchRow", "BatchResult", "folder_name", "process_sequence", "run_batch", "SCENE_PREFIX"]

log = logging.getLogger("kalmansfm")

#: ``scene:SEED`` names the built-in scene rendered with that seed instead of a path.
SCENE_PREFIX = "scene:"
BATCH_SUMMARY_FILE = "batch_summary.csv"


@dataclass(frozen=True)
class BatchRow:
    """The outcome of one sequence: ``status`` is ``ok``, ``skipped`` (already done) or ``failed``.

    ``warnings`` are the run's warnings, the same that ``demo`` prints for it.
    """

    sequence: str
    output: str
    status: str
    frames: int | None = None
    tracks: int | None = None
    fraction_tracked: float | None = None
    residual_rms_px: float | None = None
    seconds: float | None = None
    error: str | None = None
    warnings: tuple[str, ...] = ()


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
        """An aligned text table of the rows, then each row's warnings."""
        header = ["sequence", "status", "frames", "tracks", "tracked", "residual px", "seconds", "warnings", "error"]
        body = [
            [
                r.sequence,
                r.status,
                "" if r.frames is None else str(r.frames),
                "" if r.tracks is None else str(r.tracks),
                "" if r.fraction_tracked is None else f"{r.fraction_tracked:.1%}",
                "" if r.residual_rms_px is None else f"{r.residual_rms_px:.3f}",
                "" if r.seconds is None else f"{r.seconds:.1f}",
                str(len(r.warnings)) if r.warnings else "",
                r.error or "",
            ]
            for r in self.rows
        ]
        widths = [max(len(h), *(len(row[i]) for row in body)) for i, h in enumerate(header)]
        lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)).rstrip()]
        lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in body]
        lines += [f"{r.sequence}: warning: {w}" for r in self.rows for w in r.warnings]
        return "\n".join(lines)


def folder_name(spec: str) -> str:
    """The run folder name of a sequence: readable, the same in every batch, distinct for distinct inputs.

    ``scene:SEED`` gives ``scene-SEED``; a path gives its last two components (a video
    file: its name without extension) and 8 hex digits of the SHA-256 of its resolved
    path, so that ``a/images`` and ``b/images`` get different folders.

    Examples
    --------
    >>> folder_name("scene:3")
    'scene-3'
    >>> folder_name("a/images") != folder_name("b/images"), folder_name("a/images") == folder_name("./a/images")
    (True, True)
    >>> folder_name("/data/house/images")[:-9], folder_name("/data/clips/tree.avi")[:-9]
    ('house_images', 'tree')
    """
    if spec.startswith(SCENE_PREFIX):
        return "scene-" + re.sub(r"[^A-Za-z0-9.-]+", "_", spec[len(SCENE_PREFIX):])
    resolved = Path(spec).resolve()
    is_file = bool(resolved.suffix) and not resolved.is_dir() and not any(c in spec for c in "*?[")
    label = resolved.stem if is_file else "_".join(resolved.parts[-2:])
    label = re.sub(r"[^A-Za-z0-9.-]+", "_", label).strip("._") or "sequence"
    return f"{label}-{hashlib.sha256(os.fsencode(resolved)).hexdigest()[:8]}"


def _parse(spec: str) -> dict[str, Any]:
    if spec.startswith(SCENE_PREFIX):
        seed = spec[len(SCENE_PREFIX):]
        if not seed.isdigit():
            raise InvalidInputError(f"sequence {spec!r}: the built-in scene is named scene:SEED with an integer seed")
        return {"input": None, "seed": int(seed)}
    if not (Path(spec).exists() or any(ch in spec for ch in "*?[")):
        raise InvalidInputError(f"sequence {spec!r} does not exist")
    return {"input": spec}


def _row_from_summary(spec: str, out_dir: str, status: str, summary: RunSummary, seconds: float | None) -> BatchRow:
    t, f = summary.tracking, summary.reconstruction
    return BatchRow(
        spec,
        out_dir,
        status,
        frames=None if t is None else t.frames,
        tracks=None if t is None else t.tracks,
        fraction_tracked=None if t is None else t.measured_fraction,
        residual_rms_px=None if f is None else f.reprojection_rms_px,
        seconds=seconds,
        error=summary.structure_error,
        warnings=summary.all_warnings,
    )


def _finished_row(spec: str, folder: Path, source: RunSource) -> BatchRow | None:
    """The row of an earlier run in ``folder`` made from ``source``, or None if there is none."""
    try:
        summary = read_summary(folder / SUMMARY_FILE)
    except InvalidInputError:
        return None
    if summary.source != source:
        return None
    return _row_from_summary(spec, str(folder), "skipped", summary, None)


def process_sequence(spec: str, out_dir: str, options: dict[str, Any]) -> BatchRow:
    """Run the pipeline on one sequence and return its row; errors become a ``failed`` row.

    This is the function each Dask task runs; it is also usable on its own.
    """
    started = time.perf_counter()
    try:
        result = run_demo(DemoRequest(out_dir, command="batch", **_parse(spec), **options))
    except (KalmanSfmError, OSError) as exc:
        return BatchRow(spec, out_dir, "failed", seconds=time.perf_counter() - started, error=str(exc))
    except Exception as exc:  # one broken sequence must not stop the batch
        return BatchRow(
            spec, out_dir, "failed", seconds=time.perf_counter() - started, error=f"{type(exc).__name__}: {exc}"
        )
    return _row_from_summary(spec, out_dir, "ok", result.summary, time.perf_counter() - started)


def _plan(spec: str, folder: Path, options: dict[str, Any]) -> RunSource:
    """Check a sequence and its run folder before any work; the source its run would record."""
    parsed = _parse(spec)
    sequence = None if parsed["input"] is None else read_frames(parsed["input"])
    check_output_directory(folder, inputs=[parsed["input"]])
    return demo_source(DemoRequest(folder, command="batch", **parsed, **options), sequence)


def run_batch(
    sequences: Sequence[str],
    out_dir: str | Path,
    *,
    scheduler: str | None = None,
    n_workers: int | None = None,
    html: bool = False,
    progress: bool = False,
    connect_timeout_s: float = 10.0,
    **pipeline_options: Any,
) -> BatchResult:
    """Track and reconstruct every sequence as an independent task on Dask.

    Parameters
    ----------
    sequences : paths (image folders, globs, videos) or ``scene:SEED`` for the built-in scene.
    out_dir : one run folder per sequence is created inside (:func:`folder_name`), plus
        ``batch_summary.csv``.
    scheduler : address of an existing ``dask.distributed`` scheduler; None starts a
        local cluster of ``n_workers`` single-threaded worker processes.
    n_workers : local workers (default: the number of CPU cores).
    html : build each run's report.html.
    progress : a progress bar over sequences on stderr.
    connect_timeout_s : how long to try to reach ``scheduler``.
    **pipeline_options : fields of :class:`~kalmansfm.pipeline.requests.DemoRequest` that shape the
        result (``n_frames``, ``tracker``, ``camera``, ``smooth``, ``save_frames``, …).

    Returns
    -------
    BatchResult
        One row per sequence; sequences that could not run or failed are rows with
        ``status == "failed"`` and the reason in ``error``.

    Raises
    ------
    InvalidInputError
        No sequence given, none of them can run, ``n_workers`` < 1 or given with ``scheduler``, the scheduler cannot
        be reached, or ``out_dir`` cannot be written; nothing is written then.
    Interrupted
        Ctrl-C or SIGTERM; the message says how many sequences finished.
    """
    if not sequences:
        raise InvalidInputError("give at least one sequence")
    check_cluster(scheduler, n_workers)
    root = check_output_directory(out_dir, whole=False)
    options = {"html": html, **pipeline_options}

    rows: dict[int, BatchRow] = {}
    todo: list[tuple[int, str, Path]] = []
    sources: dict[int, RunSource] = {}
    first_of: dict[str, int] = {}
    for k, spec in enumerate(sequences):
        name = folder_name(spec)
        folder = root / name
        try:
            if name in first_of:
                raise InvalidInputError(f"sequence {spec!r} is sequence {first_of[name] + 1} again")
            first_of[name] = k
            source = _plan(spec, folder, options)
        except KalmanSfmError as exc:
            rows[k] = BatchRow(spec, str(folder), "failed", error=str(exc))
            continue
        finished = _finished_row(spec, folder, source)
        if finished is not None:
            rows[k] = finished
        else:
            todo.append((k, spec, folder))
            sources[k] = source
    if len(rows) == len(sequences) and all(r.status == "failed" for r in rows.values()):
        first = rows[0].error
        raise InvalidInputError(first if len(sequences) == 1 else f"none of the {len(sequences)} sequences can run; "
                                f"the first: {first}")

    if todo:
        try:
            _run_on_cluster(todo, rows, root, sequences, options, scheduler, n_workers, connect_timeout_s, progress)
        except KeyboardInterrupt as exc:
            # counted once the cluster is closed, on disk: a sequence whose run folder was swapped in finished,
            # whether or not its row had come back before the interrupt
            finished = sum(1 for k, spec, folder in todo if _finished_row(spec, folder, sources[k]) is not None)
            raise Interrupted(
                f"{finished} of {len(todo)} sequences finished (their run folders are in {root}; "
                f"{BATCH_SUMMARY_FILE} was not written); run the same command again to do the rest",
                getattr(exc, "signal_number", signal.SIGINT),
            ) from None

    ordered = tuple(rows[k] for k in range(len(sequences)))
    text = batch_summary_csv(ordered)
    root.mkdir(parents=True, exist_ok=True)
    summary_path = atomic_write(root / BATCH_SUMMARY_FILE, lambda p: p.write_text(text, encoding="utf-8"))
    return BatchResult(ordered, summary_path)


def _run_on_cluster(todo: list[tuple[int, str, Path]], rows: dict[int, BatchRow], root: Path,
                    sequences: Sequence[str], options: dict[str, Any], scheduler: str | None, n_workers: int | None,
                    connect_timeout_s: float, progress: bool) -> None:
    """Run the sequences of ``todo`` as Dask tasks and put their rows in ``rows`` as they finish."""
    from dask.distributed import as_completed

    with dask_client(scheduler, n_workers, connect_timeout_s) as client:
        root.mkdir(parents=True, exist_ok=True)
        futures = {
            client.submit(process_sequence, spec, str(folder), options, key=f"kalmansfm-{k}-{folder.name}",
                          pure=False): k
            for k, spec, folder in todo
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
                rows[k] = BatchRow(sequences[k], str(root / folder_name(sequences[k])), "failed",
                                   error=f"{type(exc).__name__}: {exc}")


def batch_summary_csv(rows: Sequence[BatchRow]) -> str:
    """``batch_summary.csv``: one line per row, the fields of :class:`BatchRow` as columns.

    Numbers as every CSV of the package writes them (:func:`kalmansfm.io._csv.number`: the
    shortest round-trip text, an empty cell for no value); texts quoted where CSV needs it;
    the warnings joined by `` | ``.

    Examples
    --------
    >>> print(batch_summary_csv([BatchRow("scene:1", "out/scene-1", "ok", 30, 8, 1.0, 0.25, float("nan"))]), end="")
    sequence,output,status,frames,tracks,fraction_tracked,residual_rms_px,seconds,error,warnings
    scene:1,out/scene-1,ok,30,8,1.0,0.25,,,
    """
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=[f.name for f in fields(BatchRow)], lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: " | ".join(v) if isinstance(v, tuple) else "" if v is None else number(v) if isinstance(v, float)
                         else v for k, v in asdict(row).items()})
    return buffer.getvalue()
