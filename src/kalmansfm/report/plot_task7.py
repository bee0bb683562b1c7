"""``task7.png``: per-axis error of the pair triangulations and of each method's estimate, with ±3σ bands."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..errors import InvalidInputError  # noqa: E402
from ..structure.landmark import METHODS  # noqa: E402
from ..structure.task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD, Task7Result, simulate_task7  # noqa: E402

__all__ = ["plot_task7", "task7_figure"]

_COLOURS = {"pairs": "tab:red", "batch": "tab:blue"}


def plot_task7(results: Sequence[Task7Result], path: str | Path) -> Path:
    """Write the per-axis error plot of one or more Task 7 runs (same noise) to ``path`` (PNG).

    The single-pair triangulation errors (grey) come from the first result; each
    result adds its estimate's error and a ±3σ band.  The y axis is symmetric-log
    because pair errors are tens of metres and fused errors about one.

    Examples
    --------
    >>> import tempfile, os
    >>> from kalmansfm.structure.task7 import simulate_task7
    >>> runs = [simulate_task7(m, seed=0) for m in ("pairs", "batch")]
    >>> with tempfile.TemporaryDirectory() as d:
    ...     out = plot_task7(runs, os.path.join(d, "task7.png"))
    ...     out.stat().st_size > 10_000
    True
    """
    if not results:
        raise InvalidInputError("plot_task7 needs at least one Task7Result")
    path = Path(path)
    first = results[0]
    it = np.arange(1, first.truth.shape[0] + 1)
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for i, (ax, name) in enumerate(zip(axes, "xyz")):
        ax.plot(it, first.measured[:, i] - first.truth[:, i], "o", color="0.55", ms=4, label="single pair")
        for r in results:
            colour = _COLOURS.get(r.method, None)
            err = r.estimate[:, i] - r.truth[:, i]
            band = 3 * r.estimate_std[:, i]
            ax.plot(it, err, "-", color=colour, lw=1.6, label=f"{r.method} estimate")
            ax.fill_between(it, -band, band, color=colour, alpha=0.15, label=f"{r.method} ±3σ")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_ylabel(f"{name} error (m)")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("iteration (image)")
    fig.suptitle(
        f"Task 7: landmark from a moving camera, f = {first.focal:g} px, noise {first.pixel_noise_std:g} px, "
        f"seed {first.seed}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def task7_figure(
    path: str | Path,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
) -> Path:
    """Simulate Task 7 once (same noise for every method) and write ``task7.png``-style plot to ``path``."""
    return plot_task7([simulate_task7(m, seed, focal, pixel_noise_std) for m in METHODS], path)
