"""Are fusion's covariances honest on real data?  The split-half test, which needs no 3-D truth.

Usage::

    python benchmarks/split_half.py                       # the table of docs/fusion.md
    python benchmarks/split_half.py --sets house --methods batch
    python benchmarks/split_half.py --data /work/shared/data

Every track seen in >= 4 views is split into two disjoint halves of its observations and each
half is fused alone with the same known cameras (``kalmansfm.fuse``, σ estimated).  With honest
covariances and *independent* errors, d = X₁ − X₂ ~ N(0, Σ₁ + Σ₂) and dᵀ(Σ₁ + Σ₂)⁻¹d ~ χ²₃
(median 2.366, 99 % below 11.34).  Splits:

* ``alternating``: observations 1, 3, 5, … against 2, 4, 6, … (the test of issue 27);
* ``contiguous``: the first half of the track's views against the second.

Both test the same covariances; with independent errors both give χ²₃.  They disagree on real
tracks: errors correlated along a track (shared by neighbouring views) are shared by the
alternating halves — d is smaller than Σ₁ + Σ₂ says — and differ between the contiguous
halves.  The serial correlation the fit measures (AR(1) over the views, per image axis:
``serial_correlation_x/y`` of the noise parameters, with standard errors) is printed with each set.

Also: the share of observations rejected against the fitted outlier share (fusing everything),
and the Model House fused with its own cameras against the dataset's points (95th percentile of
|X − dataset| / radius, radius = median distance to the median point).

Data sets (``../shared/data`` next to the repository, or ``--data``): a synthetic control
(:func:`kalmansfm.scenes.known_cameras.known_camera_scene`, 1 000 points, 12 views, 0.5 px
Gaussian noise, 2 % gross outliers, seed 1); the Oxford dinosaur (36 views, 4 983 tracks;
``viff.xy`` and ``dino_Ps.mat``, read here); the Oxford Model House (10 views, 672 tracks).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy import io as scipy_io
from scipy import stats

from kalmansfm.io.oxford import read_oxford
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.fusion import fuse
from kalmansfm.structure.geometry.pinhole import CameraSet

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"
BOUND = float(stats.chi2.ppf(0.99, 3))
OPTIONS: dict = {}


def load_dinosaur(folder: Path) -> tuple[np.ndarray, CameraSet, None]:
    """The VGG dinosaur: ``viff.xy`` (a track per row, x y per view, -1 unseen) and ``dino_Ps.mat`` (cell P)."""
    xy = np.loadtxt(folder / "viff.xy")
    views = xy.shape[1] // 2
    obs = xy.reshape(xy.shape[0], views, 2).transpose(1, 0, 2).copy()
    obs[obs == -1] = np.nan
    cells = scipy_io.loadmat(folder / "dino_Ps.mat")["P"]
    P = np.stack([np.asarray(cells[0, i], dtype=np.float64) for i in range(views)])
    return obs, CameraSet.from_matrices(P), None


def load(name: str, data: Path):
    if name == "synthetic":
        s = known_camera_scene(points=1000, views=12, pixel_std=0.5, outlier_fraction=0.02, visibility=0.6, seed=1)
        return s.observations, s.cameras, s.points
    if name == "dinosaur":
        return load_dinosaur(data / "oxford_dinosaur")
    d = read_oxford(data / "oxford_model_house")
    return d.observations, d.cameras, d.points


def split(obs: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray]:
    seen = np.isfinite(obs[..., 0])
    rank = np.cumsum(seen, axis=0) - 1
    first = rank % 2 == 0 if mode == "alternating" else rank < (seen.sum(axis=0)[None] + 1) // 2
    return (np.where((seen & first)[..., None], obs, np.nan), np.where((seen & ~first)[..., None], obs, np.nan))


def nees(d: np.ndarray, S: np.ndarray) -> np.ndarray:
    return np.einsum("ni,ni->n", d, np.linalg.solve(S, d[..., None])[..., 0])


def split_half(obs, cams, method: str, model: str, mode: str) -> dict:
    keep = np.isfinite(obs[..., 0]).sum(axis=0) >= 4
    a, b = split(obs[:, keep], mode)
    fa, fb = (fuse(h, cams, method=method, noise_model=model, **OPTIONS) for h in (a, b))
    ok = np.flatnonzero(fa.reconstructed & fb.reconstructed)
    d = fa.points[ok] - fb.points[ok]
    S = fa.point_covariances[ok] + fb.point_covariances[ok]
    plain = nees(d, S)
    return {"n": ok.size, "median": np.median(plain), "within": np.mean(plain <= BOUND)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--sets", nargs="+", default=["synthetic", "dinosaur", "house"])
    parser.add_argument("--methods", nargs="+", default=["recursive", "batch"])
    parser.add_argument("--models", nargs="+", default=["gaussian", "mixture"])
    parser.add_argument("--track-scales", action="store_true", help="give each track its own pooled scale")
    args = parser.parse_args()
    OPTIONS["track_scales"] = args.track_scales
    one, five, _ = os.getloadavg()
    print(f"# split_half: load average {one:.2f} (1 min), {five:.2f} (5 min), {os.cpu_count()} cores\n")
    print("| data | method | noise model | points | alternating: NEES median | within χ²₃ 99 % | contiguous: median "
          "| within | rejected / fitted outliers | σ (px) | serial correlation x, y | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    house_rows = []
    for name in args.sets:
        obs, cams, truth = load(name, args.data)
        for method in args.methods:
            for model in args.models:
                start = time.perf_counter()
                full = fuse(obs, cams, method=method, noise_model=model, **OPTIONS)
                alt = split_half(obs, cams, method, model, "alternating")
                con = split_half(obs, cams, method, model, "contiguous")
                seconds = time.perf_counter() - start
                p = dict(full.noise.parameters)
                rejected = full.observations.n_rejected / len(full.observations)
                share = p.get("outlier_share")
                fitted = "–" if share is None else f"{share:.4f}"
                rho = "–" if "serial_correlation_x" not in p else ", ".join(
                    f"{p[f'serial_correlation_{a}']:.2f} ± {p[f'serial_correlation_{a}_se']:.2f}" for a in "xy")
                label = model + (" + track scales" if args.track_scales and model != "gaussian" else "")
                print(f"| {name} | {method} | {label} | {alt['n']} | {alt['median']:.2f} | {alt['within']:.3f} | "
                      f"{con['median']:.2f} | {con['within']:.3f} | {rejected:.4f} / {fitted} | "
                      f"{full.noise.std:.3f} | {rho} | {seconds:.1f} |", flush=True)
                if name == "house":
                    radius = np.median(np.linalg.norm(truth - np.median(truth, axis=0), axis=1))
                    diff = np.linalg.norm(full.points - truth, axis=1) / radius
                    house_rows.append((method, label, np.nanmedian(diff), np.nanpercentile(diff, 95),
                                       int(full.reconstructed.sum())))
    if house_rows:
        print("\n| Model House with its own cameras | noise model | median |X − dataset| / radius | 95th percentile "
              "| points ok |")
        print("|---|---|---|---|---|")
        for method, model, med, p95, n in house_rows:
            print(f"| {method} | {model} | {med:.1e} | {p95:.1e} | {n} |")
    print(f"\n(χ²₃: median {stats.chi2.median(3):.3f}, 99 % bound {BOUND:.2f})")


if __name__ == "__main__":
    main()
