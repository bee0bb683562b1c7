"""Are fusion's covariances honest on real data?  The split-half test, which needs no 3-D truth.

Usage::

    python benchmarks/split_half.py                       # the table of docs/fusion.md
    python benchmarks/split_half.py --sets house --methods batch
    python benchmarks/split_half.py --data /work/shared/data
    python benchmarks/split_half.py --predict              # measured against the AR(1) model's prediction

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

``--predict`` (batch method, mixture model unless ``--methods``/``--models`` say otherwise) tests
that explanation with numbers.  The AR(1) model fitted by the full fusion (ρ_c, τ_c in the
unit of each observation's fitted σ, as ``fuse`` reports them) and each half's whitened
Jacobians at the full fusion's point (slots = views, the observations that half used) give,
per point, the model's covariances V₁, V₂ of the two halves' estimates and their cross-covariance
C₁₂ (:func:`kalmansfm.estimation.split_nees.split_covariances`), so Cov(d) = V₁ + V₂ − C₁₂ − C₂₁.
Printed for each split, measured next to predicted (:func:`~kalmansfm.estimation.split_nees.predict_nees`,
200 draws per point; ± the spread of a median over that many points):

* dᵀ(Σ₁ + Σ₂)⁻¹d, Σ_i the covariances ``fuse`` reports (independent errors) — the issue's test;
* dᵀ(V₁ + V₂)⁻¹d — the score an honest-covariance fuse would get on the issue's test (the AR(1)
  sandwich covariances in place of Σ_i; the cross term still left out, as the test does);
* dᵀ Cov(d)⁻¹d measured — χ²₃ if the AR(1) model describes the errors (the model's own check).

The whitening uses the full fusion's per-observation σ; each half's estimate weighs its
observations by its own fit, which is the same up to a constant for the default mixture model
without track scales (uniform weights within a track); with Student-t weights or track scales
the prediction's premise does not hold and its rows are not evidence.

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

from kalmansfm.estimation.noise_model import SerialCorrelation
from kalmansfm.estimation.split_nees import (
    nees_weights,
    predict_nees,
    split_covariances,
)
from kalmansfm.io.oxford import read_oxford
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.fusion import fuse
from kalmansfm.structure.geometry.pinhole import CameraSet, project_each

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


def fitted_correlation(full) -> SerialCorrelation:
    """The AR(1) model the full fusion fitted, from its reported noise parameters (independent if none)."""
    p = dict(full.noise.parameters)
    if "serial_correlation_x" not in p:
        return SerialCorrelation.independent()

    def pair(name: str, suffix: str = "") -> np.ndarray:
        return np.array([p[f"{name}_{axis}{suffix}"] for axis in "xy"])

    return SerialCorrelation(pair("serial_correlation"), pair("serial_correlation", "_se"), pair("serial_scale"),
                             pair("serial_scale", "_se"), 0)


def whitened_design(cams: CameraSet, points: np.ndarray, used: np.ndarray, std: np.ndarray) -> np.ndarray:
    """(n, V, 2, 3) Jacobians of the projections at ``points`` divided by each observation's σ, NaN where unused."""
    _, _, J = project_each(np.asarray(cams.matrices)[:, None], points[None])  # (V, n, 2, 3)
    J = J / std[..., None, None]
    return np.transpose(np.where(used[..., None, None], J, np.nan), (1, 0, 2, 3))


def predicted_split(obs, cams, full, method: str, model: str, mode: str) -> dict:
    """Measured split-half NEES next to the prediction of the full fusion's AR(1) model."""
    keep = np.isfinite(obs[..., 0]).sum(axis=0) >= 4
    a, b = split(obs[:, keep], mode)
    fa, fb = (fuse(h, cams, method=method, noise_model=model, **OPTIONS) for h in (a, b))
    ok = np.flatnonzero(fa.reconstructed & fb.reconstructed & full.reconstructed[keep])
    X = full.points[keep][ok]
    std = full.noise.observation_std
    std = np.full(obs.shape[:2], full.noise.std) if std is None else full.observations.grid(std)
    std = np.where(np.isfinite(std), std, full.noise.std)[:, keep][:, ok]
    designs = [whitened_design(cams, X, f.observations.used_mask()[:, ok], std) for f in (fa, fb)]
    cov = split_covariances(*designs, np.arange(obs.shape[0]), fitted_correlation(full))
    d = fa.points[ok] - fb.points[ok]
    reported = fa.point_covariances[ok] + fb.point_covariances[ok]
    plain, honest, model_nees = nees(d, reported), nees(d, cov.independent_sum), nees(d, cov.difference)
    p_plain, p_honest = predict_nees(reported, cov.difference), predict_nees(cov.independent_sum, cov.difference)
    # how much wider the model's covariance of one half's estimate is than the reported one (median eigenvalue)
    widening = np.median(nees_weights(fa.point_covariances[ok], cov.first))
    return {"n": ok.size, "measured": np.median(plain), "predicted": p_plain.median, "spread": p_plain.median_spread,
            "within": np.mean(plain <= BOUND), "predicted_within": p_plain.share_within(BOUND),
            "honest_predicted": p_honest.median, "honest_spread": p_honest.median_spread,
            "honest_measured": np.median(honest), "honest_within": np.mean(honest <= BOUND),
            "honest_predicted_within": p_honest.share_within(BOUND),
            "model_measured": np.median(model_nees), "model_within": np.mean(model_nees <= BOUND),
            "widening": widening}


def predict_table(args) -> None:
    methods = args.methods or ["batch"]
    models = args.models or ["mixture"]
    print("| data | method | noise model | ρ x, y (τ x, y) | split | points | reported Σ: NEES median measured | "
          "predicted | within 99 % measured | predicted | honest V₁+V₂: median predicted | measured | within 99 % "
          "predicted | measured | full Cov(d): median | within | V₁ / Σ₁ (median eigenvalue) | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.sets:
        obs, cams, _ = load(name, args.data)
        for method in methods:
            for model in models:
                full = fuse(obs, cams, method=method, noise_model=model, **OPTIONS)
                corr = fitted_correlation(full)
                rho = (f"{corr.correlation[0]:.2f}, {corr.correlation[1]:.2f} "
                       f"({corr.scale[0]:.2f}, {corr.scale[1]:.2f})")
                for mode in ("alternating", "contiguous"):
                    start = time.perf_counter()
                    r = predicted_split(obs, cams, full, method, model, mode)
                    seconds = time.perf_counter() - start
                    print(f"| {name} | {method} | {model} | {rho} | {mode} | {r['n']} | {r['measured']:.2f} | "
                          f"{r['predicted']:.2f} ± {r['spread']:.2f} | {r['within']:.3f} | {r['predicted_within']:.3f} | "
                          f"{r['honest_predicted']:.2f} ± {r['honest_spread']:.2f} | {r['honest_measured']:.2f} | "
                          f"{r['honest_predicted_within']:.3f} | {r['honest_within']:.3f} | {r['model_measured']:.2f} | "
                          f"{r['model_within']:.3f} | {r['widening']:.2f} | {seconds:.1f} |", flush=True)
    print(f"\n(χ²₃: median {stats.chi2.median(3):.3f}, 99 % bound {BOUND:.2f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--sets", nargs="+", default=["synthetic", "dinosaur", "house"])
    parser.add_argument("--methods", nargs="+", help="default: recursive and batch (with --predict: batch)")
    parser.add_argument("--models", nargs="+", help="default: gaussian and mixture (with --predict: mixture)")
    parser.add_argument("--track-scales", action="store_true", help="give each track its own pooled scale")
    parser.add_argument("--predict", action="store_true",
                        help="measured split-half NEES against the prediction of the fitted AR(1) model")
    args = parser.parse_args()
    OPTIONS["track_scales"] = args.track_scales
    one, five, _ = os.getloadavg()
    print(f"# split_half: load average {one:.2f} (1 min), {five:.2f} (5 min), {os.cpu_count()} cores\n")
    if args.predict:
        predict_table(args)
        return
    args.methods = args.methods or ["recursive", "batch"]
    args.models = args.models or ["gaussian", "mixture"]
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
