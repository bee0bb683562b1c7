"""Memory of a long sequence of short tracks: does it follow the observations, not frames × tracks?  (issue 29)

Usage::

    python benchmarks/long_sequence_memory.py                      # 20 000 frames × 50 047 tracks
    python benchmarks/long_sequence_memory.py --frames 2000 --tracks 5000
    python benchmarks/long_sequence_memory.py --keep /tmp/long      # keep the files it writes

Writes a synthetic ten-minute sequence (``tracks.csv``: frame,track_id,x,y; ``cameras.csv``: a
3 × 4 matrix per frame; ``K.csv``) — a camera moving sideways past a wall of points, each track
seen in a run of consecutive frames (geometric lengths, mean 17), 0.5 px noise and 1 % gross
mismatches — and runs each command on it in a child process, reporting the child's peak resident
memory (``ru_maxrss``), its wall time and exit code: ``kalmansfm fuse`` (with the cameras), affine
``kalmansfm reconstruct`` and ``reconstruct --camera perspective --intrinsics K.csv``.  The
issue's target: each finishes within 2 GB.  The fused points are scored against the truth (median
error in % of the mean depth) and by their NEES; the perspective cameras (reconstructed in windows)
against the true ones after one similarity: centre and rotation errors, and the scale drift; the affine
reconstruction by its reprojection RMS, the planted gross errors it rejected and the drift of its camera
rows along the sequence.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.io.reconstruction import read_reconstruction
from kalmansfm.io.structure import read_points_table
from kalmansfm.structure import Reconstruction
from kalmansfm.structure.geometry.alignment import align_similarity
from kalmansfm.structure.geometry.pinhole import CameraSet

FOCAL, WIDTH, HEIGHT = 800.0, 640, 480
STEP = 0.02  # metres the camera moves per frame


def make_sequence(frames: int, tracks: int, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, CameraSet, np.ndarray, np.ndarray]:
    """(frame, track) rows, their xy, the true cameras and points of a camera sliding along x past a wall of
    points, and which rows are planted gross errors."""
    rng = np.random.default_rng(seed)
    K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]])
    centres = np.stack([STEP * np.arange(frames), np.zeros(frames), np.zeros(frames)], axis=1)
    cams = CameraSet.from_pose(K, np.broadcast_to(np.eye(3), (frames, 3, 3)), -centres)
    length = np.minimum(rng.geometric(1 / 17, size=tracks) + 1, frames)
    start = rng.integers(0, frames - length + 1)
    depth = rng.uniform(4.0, 8.0, size=tracks)
    middle = STEP * (start + length / 2)
    half_width = 0.35 * depth * WIDTH / FOCAL
    points = np.stack([middle + rng.uniform(-half_width, half_width) * 0.5,
                       rng.uniform(-0.3, 0.3, tracks) * depth, depth], axis=1)
    track = np.repeat(np.arange(tracks), length)
    frame = np.concatenate([np.arange(s, s + n) for s, n in zip(start.tolist(), length.tolist())])
    X = np.c_[points[track], np.ones(track.size)]
    h = np.einsum("nij,nj->ni", cams.matrices[frame], X)
    xy = h[:, :2] / h[:, 2:] + rng.normal(scale=0.5, size=(track.size, 2))
    wild = rng.random(track.size) < 0.01
    xy[wild] += rng.uniform(-40, 40, size=(int(wild.sum()), 2))
    order = np.lexsort((track, frame))
    return np.c_[frame[order], track[order]], xy[order], cams, points, wild[order]


def write_inputs(folder: Path, frames: int, tracks: int) -> tuple[np.ndarray, CameraSet, np.ndarray, np.ndarray]:
    """Writes the files; returns the true points and cameras, the (frame, track) rows and which are planted gross errors."""
    index, xy, cams, points, wild = make_sequence(frames, tracks)
    with open(folder / "tracks.csv", "w") as handle:
        handle.write("frame,track_id,x,y\n")
        np.savetxt(handle, np.c_[index, xy], fmt=["%d", "%d", "%.4f", "%.4f"], delimiter=",")
    (folder / "cameras.csv").write_text(cameras_csv(cams))
    (folder / "K.csv").write_text(intrinsics_csv(np.arange(frames), cams.decompose().intrinsics))
    return points, cams, index, wild


def perspective_score(rec: Reconstruction, cams: CameraSet, points: np.ndarray, span: int = 100) -> str:
    """Cameras against the truth after one similarity (fitted on the camera centres and the points): errors and drift."""
    frames = rec.frame_ids[rec.registered]
    ok = rec.reconstructed
    n = frames.size
    fit = align_similarity(np.concatenate([rec.centres[rec.registered], rec.points[ok]]),
                           np.concatenate([cams.centers[frames], points[rec.track_ids[ok]]]))
    centres = fit.aligned[:n]
    error = np.linalg.norm(centres - cams.centers[frames], axis=1)
    path = np.sum(np.linalg.norm(np.diff(cams.centers[frames], axis=0), axis=1))
    turned = rec.rotations[rec.registered] @ fit.rotation.T @ np.swapaxes(cams.decompose().rotations[frames], 1, 2)
    angle = np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    # scale drift: each span of frames' length against the truth, in the one aligned frame
    a = np.flatnonzero(np.isin(frames + span, frames))
    b = np.searchsorted(frames, frames[a] + span)
    ratio = np.linalg.norm(centres[b] - centres[a], axis=1) / np.linalg.norm(cams.centers[frames[b]] - cams.centers[frames[a]], axis=1)
    return (f"#   {n} of {rec.n_frames} frames registered; centre error median {np.median(error):.3g} m, max "
            f"{error.max():.3g} m (path {path:.4g} m); rotation error median {np.median(angle):.3g} deg, max "
            f"{angle.max():.3g} deg; scale of {span}-frame spans {ratio.min():.3f}-{ratio.max():.3f} of the truth's")


def score_affine(out: Path, index: np.ndarray, wild: np.ndarray, frames: int) -> str:
    """The affine run's reprojection RMS over the observations it used, the planted gross errors it rejected,
    and the drift of its camera rows: |M_f| over |M*_f A| at the middle and last frames, A the affine map fitted over the
    first tenth of the frames from the true affine cameras M*_f = [[f, −f c_f, 0], [0, 0, f]] (the sliding
    scene is exactly rank 3: s = (X/Z, 1/Z, Y/Z)); 1 = no drift."""
    rec = read_reconstruction(out / "reconstruction.npz")
    obs = rec.observations
    keys = rec.frame_ids[obs.frame] * (int(index[:, 1].max()) + 1) + rec.track_ids[obs.point]
    truth_keys = index[:, 0] * (int(index[:, 1].max()) + 1) + index[:, 1]
    order = np.argsort(truth_keys)
    planted = wild[order][np.searchsorted(truth_keys[order], keys)]
    used = obs.used
    clean_used = used & ~planted
    rms = float(np.sqrt(np.mean(obs.residual[clean_used] ** 2)))
    true_rows = np.zeros((frames, 2, 3))
    true_rows[:, 0, 0], true_rows[:, 0, 1], true_rows[:, 1, 2] = FOCAL, -FOCAL * STEP * np.arange(frames), FOCAL
    registered = np.flatnonzero(np.isfinite(rec.motion).all(axis=(1, 2)))
    f_true = rec.frame_ids[registered]
    early = registered[: max(len(registered) // 10, 3)]
    a = np.linalg.lstsq(true_rows[rec.frame_ids[early]].reshape(-1, 3), rec.motion[early].reshape(-1, 3), rcond=None)[0]
    drift = [np.linalg.norm(rec.motion[k], axis=1) / np.linalg.norm(true_rows[f_true[i]] @ a, axis=1)
             for i, k in ((len(registered) // 2, registered[len(registered) // 2]), (-1, registered[-1]))]
    return (f"#   affine: {registered.size} of {frames} frames; reprojection RMS {rec.reprojection_rms:.3f} px over "
            f"the {used.sum()} observations used ({rms:.3f} px over the {clean_used.sum()} clean ones); rejected "
            f"{obs.rejected.mean():.2%} of the observations, {obs.rejected[planted].mean():.1%} of the "
            f"{planted.sum()} planted gross errors and {obs.rejected[~planted].mean():.2%} of the others; camera-row "
            f"norms / the truth's mapped from the first tenth: {drift[0][0]:.3f}, {drift[0][1]:.3f} at the middle "
            f"frame, {drift[1][0]:.3f}, {drift[1][1]:.3f} at the last")


def run(args: list[str]) -> tuple[int, float, float, str]:
    """Exit code, wall seconds, peak resident GB of ``kalmansfm args`` in a child process, and its last line."""
    script = ("import resource, sys\nfrom kalmansfm.cli.main import main\ncode = main(sys.argv[1:])\n"
              "print('PEAK', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\nsys.exit(code)\n")
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", script, *args, "--quiet"], capture_output=True, text=True)
    seconds = time.perf_counter() - started
    peak = [line for line in done.stderr.splitlines() if line.startswith("PEAK")]
    gb = int(peak[-1].split()[1]) / 1024**2 if peak else float("nan")  # ru_maxrss is in kB on Linux
    said = [line for line in (done.stdout + done.stderr).splitlines() if line.strip() and not line.startswith("PEAK")]
    return done.returncode, seconds, gb, said[-1][:300] if said else ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--tracks", type=int, default=50_047)
    parser.add_argument("--commands", default="fuse,affine,perspective")
    parser.add_argument("--keep", type=Path, help="write the inputs and runs here and keep them")
    args = parser.parse_args()
    folder = args.keep or Path(tempfile.mkdtemp(prefix="kalmansfm-long-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        started = time.perf_counter()
        points, cams, index, wild = write_inputs(folder, args.frames, args.tracks)
        n_obs = len(index)
        print(f"# {args.frames} frames x {args.tracks} tracks, {n_obs} observations "
              f"({n_obs / (args.frames * args.tracks):.3%} of frames x tracks); tracks.csv "
              f"{(folder / 'tracks.csv').stat().st_size / 1e6:.0f} MB, written in {time.perf_counter() - started:.1f} s; "
              f"load average {os.getloadavg()[0]:.1f}")
        commands = {
            "fuse": ["fuse", str(folder / "tracks.csv"), "--cameras", str(folder / "cameras.csv"), "--no-plot"],
            "affine": ["reconstruct", str(folder / "tracks.csv"), "--no-plot"],
            "perspective": ["reconstruct", str(folder / "tracks.csv"), "--camera", "perspective", "--intrinsics",
                            str(folder / "K.csv"), "--no-plot"],
        }
        print("| command | exit | wall (s) | peak memory (GB) | last line |")
        print("|---|---:|---:|---:|---|")
        for name in args.commands.split(","):
            out = folder / f"run-{name}"
            code, seconds, gb, said = run([*commands[name], "--out", str(out)])
            print(f"| {name} | {code} | {seconds:.1f} | {gb:.2f} | {said} |")
            if name == "fuse" and code == 0:
                table = read_points_table(out / "structure.csv")
                ok = np.isfinite(table.points).all(axis=1)
                error = np.linalg.norm(table.points[ok] - points[table.track_ids[ok]], axis=1)
                print(f"#   fused {ok.sum()} of {len(table.track_ids)} points; median error "
                      f"{np.median(error) / np.mean(points[:, 2]):.4%} of the mean depth")
            if name == "perspective" and code == 0:
                print(perspective_score(read_reconstruction(out / "reconstruction.npz"), cams, points))
            if name == "affine" and code == 0:
                print(score_affine(out, index, wild, args.frames))
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
