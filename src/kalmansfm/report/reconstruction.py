"""The report's one section on a reconstruction, whatever method made it, and its header cards.

Everything shown is read from the run's :class:`~kalmansfm.io.summary.ReconstructionMetrics`
(and the figures the run wrote); a row appears only when the method has that number.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..io._csv import read_rows
from ..io.run_folder import RunFolder, run_file
from ..io.summary import ReconstructionMetrics
from . import figures
from . import markup as m

__all__ = ["reconstruction_cards", "section_reconstruction"]

_MODELS = {
    ("affine", "svd"): "affine cameras: Tomasi–Kanade factorization, closed form (svd)",
    ("affine", "als"): "affine cameras: Tomasi–Kanade factorization, weighted alternating least squares (als)",
    ("affine", "sequential"): "affine cameras: factorization of a long sequence frame by frame (resection and "
                              "intersection), refined over all observations (sequential)",
    ("fusion", "recursive"): "known cameras: recursive fusion, view by view (inverse depth, iterated updates)",
    ("fusion", "batch"): "known cameras: per-point maximum likelihood (batch)",
    ("fusion", "pairs"): "known cameras: the report's fusion of consecutive two-view triangulations (pairs)",
    ("perspective", "batch"): "calibrated cameras, unknown motion: bundle adjustment (batch)",
    ("perspective", "recursive"): "calibrated cameras, unknown motion: relative orientations + recursive fusion",
    ("perspective", "segmented"): "calibrated cameras, unknown motion: bundle adjustment in windows of frames, "
                                  "chained by similarities, then fusion with the chained cameras (segmented)",
}
_FIGURES = (
    ("fusion.png", "Each point's uncertainty as views are fused: median and quartiles over points, "
                   "and the paths of the points seen most often."),
    ("reconstruction.png", "The recovered camera path (purple, frame numbers) and the points coloured by their "
                           "uncertainty √(tr Σ / 3), log scale."),
)


def _noise(r: ReconstructionMetrics) -> tuple[str, Any]:
    unit = "px" if r.noise_unit == "px" else r.noise_unit
    how = f"estimated from the residuals, {r.degrees_of_freedom} degrees of freedom" if r.noise_estimated else "given"
    return (f"noise σ ({unit}; {r.noise_model}, {how})", r.noise_std)


def reconstruction_cards(r: ReconstructionMetrics) -> list[tuple[str, str]]:
    """The header's cards of a reconstruction: frames and points kept, residual, noise, rejections."""
    cards = []
    if r.kind != "fusion":
        cards.append(("frames with a camera", f"{r.registered_frames} of {r.frames}"))
    cards.append(("points reconstructed", f"{r.reconstructed} of {r.points}"))
    if m.is_number(r.reprojection_rms_px):
        label = "factorization residual RMS" if r.kind == "affine" else "reprojection RMS"
        cards.append((label, f"{r.reprojection_rms_px:.3g} px"))
    if m.is_number(r.noise_std):
        unit = " px" if r.noise_unit == "px" else ""
        cards.append(("noise σ" + (" (estimated)" if r.noise_estimated else ""), f"{r.noise_std:.3g}{unit}"))
    if r.rejected:
        cards.append(("observations rejected", f"{r.rejected} of {r.observations}"))
    return cards


def section_reconstruction(run: RunFolder) -> str | None:
    """The reconstruction's facts, warnings and figures (None when the run made none)."""
    r = run.summary.reconstruction
    if r is None:
        if run.summary.structure_error:
            return f'<p class="warn">Not computed: {m.esc(run.summary.structure_error)}</p>'
        return None
    counts = [("ok", r.reconstructed), ("unreliable", r.unreliable), ("too few views", r.too_few_views),
              ("degenerate", r.degenerate), ("behind camera", r.behind_camera)]
    shown = [(label, n) for label, n in counts if n or label == "ok"]
    facts: list[tuple[str, Any]] = [("model", _MODELS.get((r.kind, r.method), f"{r.kind} ({r.method})"))]
    if r.camera_choice:
        facts.append(("camera model (chosen automatically)", r.camera_choice))
    if r.intrinsics:
        facts.append(("intrinsics", r.intrinsics))
    facts.append(("frames with a camera", f"{r.registered_frames} of {r.frames}"))
    if r.initial_pair is not None:
        facts.append(("initial pair (frames)", f"{r.initial_pair[0]}, {r.initial_pair[1]}"))
    facts.append(("points: " + " / ".join(label for label, _ in shown), " / ".join(str(n) for _, n in shown)))
    facts.append(("observations used / rejected as outliers / measured", f"{r.used} / {r.rejected} / {r.observations}"))
    facts.append(_noise(r))
    facts.append(("reprojection RMS of the observations used (px)", r.reprojection_rms_px))
    if r.outlier_probability is not None:
        threshold = "" if r.outlier_threshold_px is None else f"threshold {r.outlier_threshold_px:g} px, "
        facts.append(("outlier test", f"{threshold}χ² probability {r.outlier_probability:g}"))
    if r.weighted is not None:
        facts.append(("weighted by the tracker's variances", r.weighted))
    if r.smoothed is not None:
        facts.append(("smoothed tracks", r.smoothed))
    sv = [float(v) for v in r.singular_values if m.is_number(v)]
    if len(sv) >= 4 and sv[3] > 0:
        facts.append(("σ3 / σ4 (large = clearly rank 3)", sv[2] / sv[3]))
    if r.orientation is not None:
        facts.append(("scene orientation", "mirrored (points at negative depth)" if r.orientation < 0 else "normal"))
    facts.append(("median point uncertainty √(tr Σ / 3)", r.median_point_std))
    if r.median_centre_std is not None:
        facts.append(("median camera-centre uncertainty", r.median_centre_std))
    facts.append(("covariances", r.covariance_gauge))
    parts = [m.table(["", "value"], facts)]
    if r.unregistered:
        parts.append(m.frames_warning("Frames without a camera (unregistered)", r.unregistered, 12))
    if r.skipped_frames:
        parts.append(m.frames_warning("Frames with observations but no camera, skipped", r.skipped_frames, 10))
    if sv:
        listed = sv[:12]
        parts.append('<div class="two">')
        parts.append(m.figure(figures.singular_values_figure(sv),
                              "Singular values of the registered measurement matrix. Noise-free orthographic tracks "
                              "have rank 3; the values after the third measure noise and model error."))
        more = f'<p class="note">{len(sv) - len(listed)} more not listed.</p>' if len(sv) > len(listed) else ""
        parts.append("<div>" + m.table(["k", "σk"], [(k + 1, v) for k, v in enumerate(listed)]) + more + "</div></div>")
    for name, caption in _FIGURES:
        if name in run.figures:
            parts.append(m.figure(run.figures[name].read_bytes(), caption))
    parts.append(_views_and_pairs(run))
    return "".join(parts)


def _views_and_pairs(run: RunFolder) -> str:
    """A run from images: which views got a camera (and why not), and the match graph between them."""
    listed = set(run.summary.files)
    if "views.csv" not in listed or "pairs.csv" not in listed:
        return ""
    views = [fields for _, fields in read_rows(run_file(run.path, "views.csv"), required=("view", "status")).rows]
    pairs = [fields for _, fields in read_rows(run_file(run.path, "pairs.csv"), required=("i", "j")).rows]
    n = len(views)
    counts = np.zeros((n, n))
    for i, j, _, inliers in pairs:
        counts[int(i), int(j)] = counts[int(j), int(i)] = float(inliers)
    missing = [(int(v), name, status, reason) for v, name, status, reason in views if status != "registered"]
    parts = ["<h3>Views and the match graph</h3>",
             m.figure(figures.match_graph_figure(counts, [s == "registered" for _, _, s, _ in views]),
                      f"Verified matches between every pair of the {n} images that was matched (white: not matched "
                      f"or failed verification); {len(pairs)} pairs tried. Views without a camera are marked in red.")]
    if missing:
        parts.append(m.table(["view", "image", "status", "why"], missing))
    return "".join(parts)
