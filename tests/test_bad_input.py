"""Catalogue of bad input: every subcommand refuses it with exit code 2 and one line, and writes nothing.

Each row of ``CASES`` is (subcommand, arguments, a fragment the error line must contain).
``{d}`` is the folder of prepared bad inputs, ``{out}`` the output folder.  Every case
whose arguments hold ``{out}`` runs twice: with a fresh output path (it must not be
created) and with an existing folder holding an earlier result (it must stay byte for
byte as it was).  The input folder is compared byte for byte before and after as well.

"Not writable" is a path below a regular file (``{d}/a_file.txt/sub``): creating it
fails with ENOTDIR for every user, root included, on every POSIX system and on
Windows, whereas ``chmod`` does not stop root and ``/proc`` exists on Linux only.

A few cases also run as a real process to show that no traceback and no native
library warning (OpenCV, FFmpeg, Dask) reaches the terminal.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import RunSummary, summary_json
from kalmansfm.scenes import render_scene

SRC = Path(__file__).resolve().parents[1] / "src"
NOT_WRITABLE = "{d}/a_file.txt/sub"
#: Argument names of the library that a command-line user never types.
INTERNAL_NAMES = ("n_frames", "pixel_noise_std", "out_name", "occluder.", "first_frame=", "max_iterations", "gate_radius")

CASES = [
    # --- track -------------------------------------------------------------------------------
    ("track", "{d}/missing --out {out}", "missing does not exist"),
    ("track", "{d}/empty --out {out}", "empty holds no image files"),
    ("track", "{d}/text_as_png --out {out}", "text_as_png/f0.png: not a readable image"),
    ("track", "{d}/truncated --out {out}", "truncated/f1.png: not a readable image"),
    ("track", "{d}/truncated_large --out {out}", "truncated_large/f1.png: not a readable image"),
    ("track", "{d}/broken.mp4 --out {out}", "broken.mp4: not a decodable video"),
    ("track", "{d}/sizes --out {out}", "sizes/f2.png: 150×100, but f0.png is 160×120"),
    ("track", "{d}/one_frame --out {out}", "one_frame holds 1 image(s)"),
    ("track", "{d}/one_frame/f0.png --out {out}", "f0.png: a single image"),
    ("track", "{d}/good --out {out} --points {d}/outside.csv", "outside.csv: line 3: point (500, 20) lies outside"),
    ("track", "{d}/good --out {out} --points {d}/no_y.csv", "no_y.csv: line 1: missing column(s) y"),
    ("track", "{d}/good --out {out} --points {d}/nan.csv", "nan.csv: line 2: x and y must be finite"),
    ("track", "{d}/good --out {out} --points {d}/inf.csv", "inf.csv: line 2: x and y must be finite"),
    ("track", "{d}/good --out {out} --points {d}/words.csv", "words.csv: line 2: x and y must be numbers"),
    ("track", "{d}/good --out {out} --points {d}/missing.csv", "missing.csv: no such file"),
    ("track", "{d}/good --out {out} --window 0", "--window must be an odd integer >= 3; got 0"),
    ("track", "{d}/good --out {out} --window -3", "--window must be an odd integer >= 3; got -3"),
    ("track", "{d}/good --out {out} --window 4", "--window must be an odd integer >= 3; got 4"),
    ("track", "{d}/good --out {out} --window 301", "smaller than the 301-pixel window"),
    ("track", "{d}/good --out {out} --gate 0", "--gate must be in (0, 1); got 0.0"),
    ("track", "{d}/good --out {out} --gate -0.5", "--gate must be in (0, 1); got -0.5"),
    ("track", "{d}/good --out {out} --gate nan", "--gate must be in (0, 1); got nan"),
    ("track", "{d}/good --out {out} --gate-radius 0", "--gate-radius must be finite and > 0; got 0.0"),
    ("track", "{d}/good --out {out} --gate-radius -1", "--gate-radius must be finite and > 0; got -1.0"),
    ("track", "{d}/good --out {out} --gate-radius inf", "--gate-radius must be finite and > 0; got inf"),
    ("track", "{d}/good --out {out} --max-misses -1", "--max-misses must be a non-negative integer; got -1"),
    ("track", "{d}/good --out {out} --smooth-lag -2", "--smooth-lag must be a non-negative integer; got -2"),
    ("track", "{d}/good --out {out} --max-features 0", "--max-features must be an integer >= 1"),
    ("track", "{d}/good --out {out} --score sad", "argument --score: invalid choice"),
    ("track", "{d}/good --out {out} --matcher nearest", "argument --matcher: invalid choice"),
    ("track", "{d}/good --out {out} --matcher search --window 301", "smaller than the 301-pixel window"),
    ("track", "{d}/good --out " + NOT_WRITABLE, "a_file.txt/sub is not writable"),
    ("track", "{d}/good --out {d}/a_file.txt", "a_file.txt exists and is not a folder"),
    ("track", "{d}/good --out {d}/good", "output folder {d}/good is the input {d}/good"),
    ("track", "{d}/good --out {d}/good/run", "output folder {d}/good/run lies inside the input {d}/good"),
    ("track", "{d}/good --out {d}/not_a_run", "not_a_run is not empty and holds no kalmansfm run"),
    ("track", "{d}/good --out {d}/run_with_notes", "holds notes.txt, which its kalmansfm run did not write"),
    ("track", "{d}/good --out {out} --points {d}/big_id.csv", "big_id.csv: line 2: track_id must be an integer in 0 … 10000000; got '1e23'"),
    ("track", "{d}/good --out {out} --gate-radius 1e-300", "--gate-radius must be between 1e-06 and 1e+06; got 1e-300"),
    ("track", "{d}/good --out {out} --gate-radius 1e300", "--gate-radius must be between 1e-06 and 1e+06; got 1e+300"),
    # --- demo --------------------------------------------------------------------------------
    ("demo", "--out {out} --frames 1", "--frames must be an integer >= 3; got 1"),
    ("demo", "--out {out} --frames 0", "--frames must be an integer >= 3; got 0"),
    ("demo", "--out {out} --frames -3", "--frames must be an integer >= 3; got -3"),
    ("demo", "--out {out} --seed -1", "--seed must be a non-negative integer; got -1"),
    ("demo", "--out {out} --input {d}/missing", "missing does not exist"),
    ("demo", "--out {out} --input {d}/empty", "empty holds no image files"),
    ("demo", "--out {out} --input {d}/text_as_png", "text_as_png/f0.png: not a readable image"),
    ("demo", "--out {out} --input {d}/truncated", "truncated/f1.png: not a readable image"),
    ("demo", "--out {out} --input {d}/broken.mp4", "broken.mp4: not a decodable video"),
    ("demo", "--out {out} --input {d}/sizes", "sizes/f2.png: 150×100, but f0.png is 160×120"),
    ("demo", "--out {out} --input {d}/one_frame", "one_frame holds 1 image(s)"),
    ("demo", "--out " + NOT_WRITABLE + " --frames 3", "a_file.txt/sub is not writable"),
    ("demo", "--out {d}/good/demo --input {d}/good", "output folder {d}/good/demo lies inside the input {d}/good"),
    # --- reconstruct -------------------------------------------------------------------------
    ("reconstruct", "{d}/missing.csv --out {out}", "missing.csv: no such file"),
    ("reconstruct", "{d}/empty --out {out}", "empty: a folder without tracks.npz"),
    ("reconstruct", "{d}/tracks_no_y.csv --out {out}", "tracks_no_y.csv: line 1: missing column(s) y; expected frame,track_id,x,y"),
    ("reconstruct", "{d}/tracks_nan.csv --out {out}", "tracks_nan.csv: line 3: y must be finite; got 'nan'"),
    ("reconstruct", "{d}/tracks_inf.csv --out {out}", "tracks_inf.csv: line 3: x must be finite; got 'inf'"),
    ("reconstruct", "{d}/tracks_words.csv --out {out}", "tracks_words.csv: line 2: frame must be an integer"),
    ("reconstruct", "{d}/tracks_ragged.csv --out {out}", "tracks_ragged.csv: line 3: 3 fields, the header has 4"),
    ("reconstruct", "{d}/binary.csv --out {out}", "binary.csv: not a readable text CSV (not UTF-8"),
    ("reconstruct", "{d}/positions_3.npz --out {out}", "positions_3.npz: positions must be a numeric (frames, points, 2)"),
    ("reconstruct", "{d}/status_shape.npz --out {out}", "status_shape.npz: status must be an integer (4, 5) array"),
    ("reconstruct", "{d}/no_ids.npz --out {out}", "no_ids.npz: missing array(s) track_ids"),
    ("reconstruct", "{d}/text.npz --out {out}", "text.npz: not a readable NPZ file"),
    ("reconstruct", "{d}/too_few.csv --out {out}", "factorize needs >= 3 frames and >= 4 points"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --max-iterations 0", "--max-iterations must be an integer >= 1; got 0"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --max-iterations -5", "--max-iterations must be an integer >= 1; got -5"),
    ("reconstruct", "{d}/tracks_ok.csv --out " + NOT_WRITABLE, "a_file.txt/sub is not writable"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective", "needs its calibration"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective --focal 500", "--focal needs the image size"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective --intrinsics {d}/K_singular.csv",
     "K_singular.csv: line 2: fx and fy must be > 0"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective --intrinsics {d}/K_two_frames.csv",
     "K_two_frames.csv: no intrinsics for frame 2"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective --focal 500 --image-size 100 100",
     "no two frames share >= 24 tracks"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --focal 500", "describe a perspective camera"),
    ("reconstruct", "{out}/tracks.csv --out {out}", "tracks.csv lies inside the output folder"),
    ("reconstruct", "{d}/tracks_big_frame.csv --out {out}", "tracks_big_frame.csv: line 2: frame must be in 0 … 10000000; got 1e30"),
    ("reconstruct", "{d}/tracks_big_id.csv --out {out}", "line 3: track_id must be in 0 … 10000000; got 1e30"),
    ("reconstruct", "{d}/tracks_same_point.csv --out {out}", "factorize needs points that spread out"),
    ("reconstruct", "{d}/tracks_huge_x.csv --out {out}", "tracks_huge_x.csv: line 10: x must be within ±1e+07 px; got '1e300'"),
    ("reconstruct", "{d}/tracks_case.csv --out {out}", "line 2: status must be measured, predicted, lost, initialising; got 'Measured'"),
    ("reconstruct", "{d}/complex.npz --out {out}", "complex.npz: positions must be a numeric (frames, points, 2) array; got complex128"),
    ("reconstruct", "{d}/negative_frames.npz --out {out}", "negative_frames.npz: frames must be increasing frame numbers"),
    ("reconstruct", "{d}/repeated_frames.npz --out {out}", "repeated_frames.npz: frames must be increasing frame numbers"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --camera perspective --intrinsics {out}/K.csv",
     "K.csv lies inside the output folder"),
    ("reconstruct", "{d}/tracks_ok.csv --out {d}/not_a_run --camera auto --focal 500 --image-size 100 100",
     "not_a_run is not empty and holds no kalmansfm run"),
    ("demo", "--out {out} --camera perspective --focal 500", "needs your own sequence"),
    ("demo", "--input {d}/good --out {d}/good/run --camera perspective --focal 500",
     "output folder {d}/good/run lies inside the input {d}/good"),
    # --- fuse --------------------------------------------------------------------------------
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_no_p34.csv --out {out}", "cams_no_p34.csv: line 1: missing column(s) p34 of the projection-matrix layout"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_singular.csv --out {out}", "cams_singular.csv: line 3: frame 1: not a camera"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_nan.csv --out {out}", "cams_nan.csv: line 2: p11 must be finite"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_twice.csv --out {out}", "cams_twice.csv: lines 2 and 3: frame 0 has two cameras"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_not_rotation.csv --out {out}", "cams_not_rotation.csv: line 2: r11..r33 is not a rotation"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_one.csv --out {out}", "tracks_ok.csv: 1 of its 4 frame(s) have a camera"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/missing.csv --out {out}", "missing.csv: no such file"),
    ("fuse", "{d}/tracks_no_y.csv --cameras {d}/cams_ok.csv --out {out}", "tracks_no_y.csv: line 1: missing column(s) y; expected frame,track_id,x,y"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --pixel-std -1", "--pixel-std must be finite and > 0"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --pixel-std some", "argument --pixel-std"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --outlier-prob 2", "--outlier-prob must be in (0, 1]"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --method ekf", "argument --method: invalid choice"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --workers 0", "workers must be an integer >= 1"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --workers 0", "--workers must be an integer >= 1; got 0"),
    ("reconstruct", "{d}/tracks_ok.csv --out {out} --workers 2", "--workers and --scheduler spread the matching of image pairs"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out " + NOT_WRITABLE, "a_file.txt/sub is not writable"),
    ("fuse", "{out}/tracks.csv --cameras {d}/cams_ok.csv --out {out}", "tracks.csv lies inside the output folder"),
    ("fuse", "{d}/tracks_ok.csv --cameras {out}/cameras.csv --out {out}", "cameras.csv lies inside the output folder"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {d}/not_a_run", "not_a_run is not empty and holds no kalmansfm run"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {d}/run_with_notes", "holds notes.txt, which its kalmansfm run did not write"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --scheduler notaurl", "cannot use the Dask scheduler 'notaurl'"),
    # issue 30: a pipe, a device or a link loop given as a file; values too large to compute with
    ("fuse", "{d}/tracks_ok.csv --cameras /dev/zero --out {out}", "/dev/zero is a character device, not a file (given as --cameras)"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/fifo.csv --out {out}", "fifo.csv is a named pipe (FIFO), not a file (given as --cameras)"),
    ("fuse", "{d}/loop.csv --cameras {d}/cams_ok.csv --out {out}", "loop.csv is a symbolic link loop (given as TRACKS)"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {out} --pixel-std 1e300",
     "--pixel-std must be between 1e-09 and 1e+06 pixels"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {d}/only_git", "only_git is not empty and holds no kalmansfm run"),
    ("fuse", "{d}/tracks_ok.csv --cameras {d}/cams_ok.csv --out {d}/run_with_html", "holds mine.html, which its kalmansfm run did not write"),
    ("track", "{d}/fifo.avi --out {out}", "fifo.avi is a named pipe (FIFO), not a file (given as INPUT)"),
    ("demo", "--out {out} --input {d}/fifo.avi", "fifo.avi is a named pipe (FIFO), not a file (given as --input)"),
    ("demo", "--out {out} --frames 100000000", "--frames 100000000 of 320x240 would need about"),
    # --- report (its output folder is the run folder itself) ----------------------------------
    ("report", "{d}/missing", "missing does not exist or is not a folder"),
    ("report", "{d}/empty", "empty/summary.json: not found"),
    ("report", "{d}/a_file.txt", "a_file.txt does not exist or is not a folder"),
    ("report", "{d}/run_bad_json", "run_bad_json/summary.json: line 1: not valid JSON"),
    ("report", "{d}/run_bad_npz", "run_bad_npz/tracks.npz: positions must be a numeric (frames, points, 2) array"),
    ("report", "{d}/run_bad_structure", "run_bad_structure/structure.csv: line 2: column 'Y' must be a number"),
    ("report", "{d}/run_bad_json --name ../escape.html", "--name must be a plain file name"),
    ("report", "{d}/run_bad_frame", "run_bad_frame/frames/frame_000.png: cannot be read as a PNG image"),
    ("report", "{d}/run_ok --name summary.json", "--name summary.json would overwrite the run's own summary.json"),
    ("report", "{d}/run_ok --name tracks.csv", "--name tracks.csv would overwrite the run's own tracks.csv"),
    ("report", "{d}/run_ok --name notes.txt", "--name must end in .html"),
    ("report", "{d}/run_escapes", "run_escapes/summary.json: lists '../tracks_ok.csv', which is not a file of the run folder"),
    ("report", "{d}/run_absolute", "run_absolute/summary.json: lists '/etc/hostname', which is not a file of the run folder"),
    # --- batch -------------------------------------------------------------------------------
    ("batch", "{d}/missing --out {out}", "sequence '{d}/missing' does not exist"),
    ("batch", "scene:x {d}/missing --out {out}", "none of the 2 sequences can run; the first: sequence 'scene:x'"),
    ("batch", "{d}/empty --out {out}", "empty holds no image files"),
    ("batch", "{d}/one_frame --out {out}", "one_frame holds 1 image(s)"),
    ("batch", "scene:1 --out {out} --scheduler notaurl", "cannot use the Dask scheduler 'notaurl'"),
    ("batch", "scene:1 --out {out} --workers 0", "--workers must be an integer >= 1; got 0"),
    ("batch", "scene:1 --out {out} --workers -2", "--workers must be an integer >= 1"),
    ("batch", "scene:1 --out {out} --workers 2 --scheduler tcp://nowhere:1", "--workers (a local cluster) or --scheduler (an existing one), not both"),
    ("batch", "scene:1 --out " + NOT_WRITABLE, "a_file.txt/sub is not writable"),
    # --- tables ------------------------------------------------------------------------------
    ("tables", "--task 0", "unknown task 0; tasks 1-6"),
    ("tables", "--task 8", "unknown task 8"),
    ("tables", "--task -1", "unknown task -1"),
    ("tables", "--task two", "argument --task: invalid int value"),
    ("tables", "--task 7 --pixel-std 0", "--pixel-std must be finite and > 0"),
    ("tables", "--task 7 --pixel-noise -1", "--pixel-std must be finite and > 0"),
    ("tables", "--task 7 --focal 0", "--focal must be finite and > 0"),
    ("tables", "--task 7 --focal inf", "--focal must be finite and > 0"),
    ("tables", "--task 7 --seed -1", "--seed must be a non-negative integer"),
    # --- consistency -------------------------------------------------------------------------
    ("consistency", "--task 3", "argument --task: invalid choice: 3"),
    ("consistency", "--task 2 --runs 0", "--runs must be an integer >= 2; got 0"),
    ("consistency", "--task 2 --runs -1", "--runs must be an integer >= 2"),
    ("consistency", "--task 2 --method pairs", "--method applies to --task 7 only"),
    ("consistency", "--task 7 --runs 3 --pixel-noise -1", "--pixel-std must be finite and > 0"),
    ("consistency", "--task 7 --runs 3 --pixel-std 0", "--pixel-std must be finite and > 0"),
    ("consistency", "--task 7 --runs 3 --focal nan", "--focal must be finite and > 0"),
    ("consistency", "--task 2 --runs 10000000000", "--runs must be an integer in 2 … 100000; got 10000000000 (about 2 days"),
    ("consistency", "--task 7 --runs 10000000000", "--runs must be an integer in 2 … 100000; got 10000000000 (about"),
    # --- scene -------------------------------------------------------------------------------
    ("scene", "--out {out} --frames 1", "--frames must be an integer >= 3; got 1"),
    ("scene", "--out {out} --size 0x10", "--size must be (width, height) with integers in 32 … 4096; got (0, 10)"),
    ("scene", "--out {out} --size 40000x40000", "--size must be (width, height) with integers in 32 … 4096"),
    ("scene", "--out {out} --size big", "argument --size: expected WIDTHxHEIGHT"),
    ("scene", "--out {out} --noise -1", "--noise must be a finite number >= 0; got -1.0"),
    ("scene", "--out {out} --noise nan", "--noise must be a finite number >= 0"),
    ("scene", "--out {out} --seed -1", "--seed must be a non-negative integer"),
    ("scene", "--out {out} --occluder 99,1,1", "--occluder TRACK must be in 0 … 9; got 99"),
    ("scene", "--out {out} --occluder 2,-1,0", "--occluder TRACK,FIRST,N must hide at least one frame within 0 … 29; got 0 frame(s) from frame -1"),
    ("scene", "--out {out} --occluder-marker", "--occluder-marker needs --occluder"),
    ("scene", "--out " + NOT_WRITABLE, "a_file.txt/sub is not writable"),
    ("scene", "--out {out} --frames 100000000", "--frames 100000000 of 320x240 would need about"),
]


def _params():
    for command, arguments, fragment, *marks in CASES:
        name = f"{command} {arguments}".replace("{d}/", "").replace("{out}", "OUT")
        variants = ["new", "existing"] if "{out}" in arguments else ["none"]
        for variant in variants:
            yield pytest.param(command, arguments, fragment, variant, id=f"{name} [{variant}]", marks=marks)


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


@pytest.fixture(scope="module")
def bad_inputs(tmp_path_factory) -> Path:
    """A folder holding one example of every kind of bad input (and a few good ones)."""
    d = tmp_path_factory.mktemp("bad_inputs")
    scene = render_scene(n_frames=5, image_size=(160, 120))
    frames = [_png(f) for f in scene.frames]

    def folder(name: str, files: dict[str, bytes]) -> None:
        (d / name).mkdir()
        for file, data in files.items():
            (d / name / file).write_bytes(data)

    folder("good", {f"f{k}.png": png for k, png in enumerate(frames)})
    folder("empty", {})
    folder("text_as_png", {f"f{k}.png": b"this is text, not a picture\n" for k in range(3)})
    folder("truncated", {"f0.png": frames[0], "f1.png": frames[1][: len(frames[1]) // 2], "f2.png": frames[2]})
    # a frame cut inside its image data: libpng itself prints "PNG input buffer is incomplete"
    large = [_png(f) for f in render_scene(n_frames=3).frames]
    folder("truncated_large", {"f0.png": large[0], "f1.png": large[1][: len(large[1]) // 2], "f2.png": large[2]})
    folder("sizes", {"f0.png": frames[0], "f1.png": frames[1], "f2.png": _png(scene.frames[2][:100, :150])})
    folder("one_frame", {"f0.png": frames[0]})
    (d / "broken.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(300))
    (d / "a_file.txt").write_text("a regular file, so nothing can be created below it\n")

    (d / "outside.csv").write_text("x,y\n10,10\n500,20\n")
    (d / "no_y.csv").write_text("x,z\n1,2\n")
    (d / "nan.csv").write_text("x,y\n10,nan\n")
    (d / "inf.csv").write_text("x,y\n10,inf\n")
    (d / "words.csv").write_text("x,y\n10,abc\n")

    rng = np.random.default_rng(0)
    ok_rows = [f"{f},{p},{x:.3f},{y:.3f}" for f in range(4) for p in range(6) for x, y in [rng.uniform(0, 100, 2)]]
    (d / "tracks_ok.csv").write_text("frame,track_id,x,y\n" + "\n".join(ok_rows) + "\n")
    # a perspective sequence (40 points, 5 views) that reconstruct --camera perspective can try
    points, rows = rng.uniform(-1, 1, (40, 3)), []
    for f in range(5):
        a = 0.1 * f
        camera = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        seen = points @ camera.T + [0, 0, 5]
        xy = 500 * seen[:, :2] / seen[:, 2:] + 320
        rows += [f"{f},{p},{xy[p, 0]:.3f},{xy[p, 1]:.3f}" for p in range(40)]
    (d / "perspective.csv").write_text("frame,track_id,x,y\n" + "\n".join(rows) + "\n")
    (d / "K_singular.csv").write_text("frame,fx,fy,cx,cy,skew\n0,500,0,50,50,0\n")
    (d / "K_two_frames.csv").write_text("frame,fx,fy,cx,cy,skew\n0,500,500,50,50,0\n1,500,500,50,50,0\n")
    (d / "tracks_no_y.csv").write_text("frame,track_id,x\n0,1,2\n")
    (d / "tracks_nan.csv").write_text("frame,track_id,x,y\n0,1,2,3\n1,1,2,nan\n")
    (d / "tracks_inf.csv").write_text("frame,track_id,x,y\n0,1,2,3\n1,1,inf,3\n")
    (d / "tracks_words.csv").write_text("frame,track_id,x,y\nfirst,1,2,3\n")
    (d / "tracks_ragged.csv").write_text("frame,track_id,x,y\n0,1,2,3\n1,1,2\n")
    (d / "too_few.csv").write_text("frame,track_id,x,y\n0,1,2,3\n1,1,2,3\n")
    p_header = "frame," + ",".join(f"p{i}{j}" for i in range(1, 4) for j in range(1, 5))
    p_rows = [f"{f},500,0,320,{-100 * f},0,500,240,0,0,0,1,10" for f in range(4)]
    (d / "cams_ok.csv").write_text(p_header + "\n" + "\n".join(p_rows) + "\n")
    (d / "cams_no_p34.csv").write_text(p_header.rsplit(",", 1)[0] + "\n0" + ",1" * 11 + "\n")
    (d / "cams_singular.csv").write_text(p_header + "\n" + p_rows[0] + "\n1,1,2,3,0,2,4,6,0,0,0,1,0\n")
    (d / "cams_nan.csv").write_text(p_header + "\n0,nan" + ",1" * 11 + "\n")
    (d / "cams_twice.csv").write_text(p_header + "\n" + p_rows[0] + "\n" + p_rows[0] + "\n")
    (d / "cams_one.csv").write_text(p_header + "\n" + p_rows[0] + "\n")
    k_header = "frame,fx,fy,cx,cy,skew," + ",".join(f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)) + ",t1,t2,t3"
    (d / "cams_not_rotation.csv").write_text(k_header + "\n0,500,500,320,240,0,1,0,0,0,2,0,0,0,1,0,0,5\n")
    (d / "binary.csv").write_bytes(bytes(range(256)))
    (d / "big_id.csv").write_text("x,y,track_id\n50,50,1e23\n60,60,2\n")
    (d / "tracks_big_frame.csv").write_text("frame,track_id,x,y\n1e30,1,2,3\n0,1,2,3\n")
    (d / "tracks_big_id.csv").write_text("frame,track_id,x,y\n0,1,2,3\n0,1e30,2,3\n")
    same = [f"{f},{p},10,10" for f in range(4) for p in range(6)]
    (d / "tracks_same_point.csv").write_text("frame,track_id,x,y\n" + "\n".join(same) + "\n")
    huge = ok_rows[:8] + ["1,2,1e300,5"] + ok_rows[9:]  # frame 1, track 2 far out
    (d / "tracks_huge_x.csv").write_text("frame,track_id,x,y\n" + "\n".join(huge) + "\n")
    (d / "tracks_case.csv").write_text("frame,track_id,x,y,status\n0,1,2,3,Measured\n")
    arrays = {"positions": rng.uniform(0, 100, (4, 5, 2)), "status": np.ones((4, 5), np.int8), "track_ids": np.arange(5)}
    np.savez(d / "complex.npz", **{**arrays, "positions": arrays["positions"] + 1j})
    np.savez(d / "negative_frames.npz", **arrays, frames=np.array([-1, 0, 1, 2]))
    np.savez(d / "repeated_frames.npz", **arrays, frames=np.array([0, 1, 1, 2]))
    np.savez(d / "positions_3.npz", positions=np.zeros((4, 5, 3)), status=np.ones((4, 5), np.int8), track_ids=np.arange(5))
    np.savez(d / "status_shape.npz", positions=np.zeros((4, 5, 2)), status=np.ones((4, 4), np.int8), track_ids=np.arange(5))
    np.savez(d / "no_ids.npz", positions=np.zeros((4, 5, 2)), status=np.ones((4, 5), np.int8))
    (d / "text.npz").write_text("not a zip archive\n")

    def summary(*files: str) -> bytes:
        return summary_json(RunSummary(command="track", input="x", files=(*files, "summary.json"))).encode()

    folder("run_bad_json", {"summary.json": b"{ not json"})
    folder("run_bad_npz", {"summary.json": summary("tracks.npz")})
    np.savez(d / "run_bad_npz" / "tracks.npz", positions=np.zeros((3, 4, 3)), status=np.zeros((3, 4), np.int8),
             track_ids=np.arange(4))
    folder("run_bad_structure", {"summary.json": summary("structure.csv"), "structure.csv": b"track_id,X,Y,Z\n1,2,abc,4\n"})
    folder("run_bad_frame", {"summary.json": summary("frames/frame_000.png")})
    folder("run_bad_frame/frames", {"frame_000.png": large[1][: len(large[1]) // 2]})
    folder("run_ok", {"summary.json": summary("tracks.csv"), "tracks.csv": b"frame,track_id,x,y\n0,1,2,3\n"})
    folder("not_a_run", {"notes.txt": b"the user's own file\n"})
    folder("only_git", {})
    folder("only_git/.git", {"HEAD": b"ref: refs/heads/main\n"})
    folder("run_with_html", {"summary.json": summary("tracks.csv"), "tracks.csv": b"frame,track_id,x,y\n0,1,2,3\n",
                             "mine.html": b"<p>the user's own page</p>\n"})
    folder("run_escapes", {"summary.json": summary("../tracks_ok.csv")})
    folder("run_absolute", {"summary.json": summary("/etc/hostname")})
    if hasattr(os, "mkfifo"):
        os.mkfifo(d / "fifo.csv")
        os.mkfifo(d / "fifo.avi")
    (d / "loop.csv").symlink_to(d / "loop.csv")
    folder("run_with_notes", {"summary.json": summary("tracks.csv"), "tracks.csv": b"frame,track_id,x,y\n0,1,2,3\n",
                              "notes.txt": b"the user's own file\n"})
    return d


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file below ``root`` with its bytes (empty when ``root`` does not exist)."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _argv(command: str, arguments: str, d: Path, out: Path) -> list[str]:
    return [command, *arguments.format(d=d, out=out).split(), "--quiet"]


def _run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse refuses a usage error by exiting
        return int(exc.code)


@pytest.mark.parametrize("command, arguments, fragment, variant", list(_params()))
def test_bad_input_is_refused_in_one_line_and_nothing_is_written(
    command, arguments, fragment, variant, bad_inputs, tmp_path, capsys
):
    out = tmp_path / "out"
    if variant == "existing":  # an earlier run that the bad one must leave as it was
        out.mkdir()
        earlier = RunSummary(command="reconstruct", input="earlier.csv", files=("tracks.csv", "summary.json"))
        (out / "summary.json").write_text(summary_json(earlier))
        (out / "tracks.csv").write_text("frame,track_id,x,y\n0,1,2,3\n")
    before_out, before_inputs = _snapshot(out), _snapshot(bad_inputs)

    code = _run(_argv(command, arguments, bad_inputs, out))

    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code == 2, captured.err
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"kalmansfm {command}: error: "), lines[0]
    assert fragment.format(d=bad_inputs) in lines[0]
    # the message names what the user typed: no raw error number, no library argument names
    assert "Errno" not in lines[0]
    assert not [name for name in INTERNAL_NAMES if name in lines[0]], lines[0]
    assert "Traceback" not in captured.err
    assert captured.out == ""
    assert _snapshot(out) == before_out
    assert out.exists() == (variant == "existing")
    assert _snapshot(bad_inputs) == before_inputs
    assert not [p for p in bad_inputs.rglob("*.tmp")]
    assert sorted(p.name for p in tmp_path.iterdir()) == (["out"] if variant == "existing" else [])


@pytest.mark.parametrize(
    "arguments, fragment",
    [
        ("track {d}/truncated --out {out} --quiet", "truncated/f1.png: not a readable image"),
        ("track {d}/truncated_large --out {out} --quiet", "truncated_large/f1.png: not a readable image"),
        ("report {d}/run_bad_frame --quiet", "frame_000.png: cannot be read as a PNG image"),
        ("track {d}/broken.mp4 --out {out} --quiet", "broken.mp4: not a decodable video"),
        ("reconstruct {d}/tracks_nan.csv --out {out} --quiet", "line 3: y must be finite"),
        ("batch scene:1 --out {out} --workers 0 --quiet", "--workers must be an integer >= 1"),
        ("track {d}/good --out {out} --window 4", "--window must be an odd integer >= 3; got 4"),
        ("reconstruct {d}/complex.npz --out {out}", "positions must be a numeric"),  # no ComplexWarning
        ("consistency --task 2 --runs 0", "runs must be an integer >= 2; got 0"),  # no progress bar first
        ("batch scene:1 --out {out} --scheduler notaurl", "cannot use the Dask scheduler 'notaurl'"),
        # NumPy's "overflow encountered" warnings used to come first (issue 30)
        ("reconstruct {d}/perspective.csv --out {out} --camera perspective --focal 1e-300 --image-size 640 480 --quiet",
         "--focal must be between 0.001 and 1e+07 pixels"),
        ("fuse {d}/tracks_ok.csv --cameras {d}/fifo.csv --out {out}", "fifo.csv is a named pipe (FIFO)"),  # no hang
    ],
)
def test_a_real_process_prints_one_line_and_no_native_warnings(arguments, fragment, bad_inputs, tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    env.pop("OPENCV_FFMPEG_LOGLEVEL", None)
    result = subprocess.run(
        [sys.executable, "-m", "kalmansfm", *arguments.format(d=bad_inputs, out=out).split()],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert fragment in result.stderr
    assert "Traceback" not in result.stderr
    assert not out.exists()


def test_with_a_progress_bar_the_error_is_still_the_last_line_and_no_traceback(bad_inputs, tmp_path):
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "kalmansfm", "track", str(bad_inputs / "truncated"), "--out", str(out)],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(SRC)}, timeout=120,
    )
    assert result.returncode == 2
    # tqdm's bar (leave=False) is erased on a terminal; what stays is the error line
    assert result.stderr.rstrip("\n").splitlines()[-1].startswith("kalmansfm track: error: ")
    assert "Traceback" not in result.stderr and "WARN" not in result.stderr
    assert not out.exists()
