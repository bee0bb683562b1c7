"""What a run folder promises, command by command (docs/robustness.md, "Guarantees").

* no stale files: after a successful rerun the folder holds exactly the files its summary.json
  lists (and the report), whatever an earlier run left there;
* identity: summary.json records what the run was made from (resolved input, files, options);
* the report of a run mentions nothing of an earlier run in the same folder.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.io.tracks import observations_csv
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure.geometry.pinhole import CameraSet

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src"
HOUSE = ROOT.parent / "shared" / "data" / "cmu_house" / "images"
REPORT_TRACKS = SRC / "kalmansfm" / "data" / "report_polyhedron_tracks.csv"


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}


def _owns_exactly_its_files(folder: Path) -> None:
    """The folder holds what its summary lists (plus report.html), nothing more, and no temporaries beside it."""
    listed = set(read_summary(folder / "summary.json").files)
    assert _files(folder) - {"report.html"} == listed
    assert [p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}.")] == []


def _run(*argv: str) -> None:
    assert main([*argv, "--quiet"]) == 0


def test_reconstruct_without_plot_over_a_run_with_plot_leaves_no_old_picture(tmp_path):
    out = tmp_path / "shape"
    _run("reconstruct", str(REPORT_TRACKS), "--out", str(out))
    assert (out / "structure.png").exists()
    _run("reconstruct", str(REPORT_TRACKS), "--out", str(out), "--no-plot")
    assert not (out / "structure.png").exists()
    _owns_exactly_its_files(out)


def test_a_shorter_scene_over_a_longer_one_leaves_only_its_own_frames(tmp_path):
    out = tmp_path / "scene"
    _run("scene", "--out", str(out), "--frames", "9")
    _run("scene", "--out", str(out), "--frames", "4")
    assert sorted(p.name for p in out.glob("frame_*.png")) == [f"frame_{k:03d}.png" for k in range(4)]
    _owns_exactly_its_files(out)
    assert [name for name, _ in read_summary(out / "summary.json").source.options] == ["scene"]


@pytest.mark.skipif(not HOUSE.is_dir(), reason="needs ../shared/data/cmu_house")
def test_demo_runs_of_different_inputs_into_one_folder_do_not_mix(tmp_path):
    """Issue 16.1: the second report mentions nothing of the first, in either order."""
    clip = tmp_path / "house"
    clip.mkdir()
    for k in range(8):
        shutil.copy(HOUSE / f"house.seq{k}.png", clip / f"house.seq{k}.png")
    out = tmp_path / "kalmansfm-demo"

    _run("demo", "--out", str(out), "--frames", "6")
    assert (out / "ground_truth_tracks.csv").exists()
    _run("demo", "--out", str(out), "--input", str(clip))
    _owns_exactly_its_files(out)
    assert not list(out.glob("ground_truth_*")) and len(list((out / "frames").iterdir())) == 8
    report = (out / "report.html").read_text()
    assert "ground_truth" not in report and "Comparison with ground truth" not in report
    assert "built-in scene" not in report

    _run("demo", "--out", str(out), "--frames", "6")  # and back: no frames of the clip stay
    _owns_exactly_its_files(out)
    assert len(list((out / "frames").iterdir())) == 6
    report = (out / "report.html").read_text()
    assert str(clip) not in report and "house.seq" not in report


def test_every_command_records_what_it_was_made_from(tmp_path):
    scene = tmp_path / "scene"
    _run("scene", "--out", str(scene), "--frames", "5")
    _run("track", str(scene), "--out", str(tmp_path / "tracks"), "--points", str(scene / "points.csv"))
    _run("reconstruct", str(tmp_path / "tracks" / "tracks.npz"), "--out", str(tmp_path / "shape"))
    track = read_summary(tmp_path / "tracks" / "summary.json").source
    assert track.input == str(scene.resolve())
    assert track.files == 6  # 5 frames and points.csv
    assert dict(track.options)["smooth"] == "false"
    shape = read_summary(tmp_path / "shape" / "summary.json").source
    assert shape.input == str((tmp_path / "tracks" / "tracks.npz").resolve()) and shape.files == 1
    camera = json.loads(dict(shape.options)["camera"])
    assert camera["model"] == "affine" and camera["weighted"] is True
    assert read_summary(scene / "summary.json").source.input == "built-in scene (seed 0, 5 frames)"


def test_importing_the_command_line_loads_nothing_heavy():
    """The console entry point sets up Ctrl-C and SIGTERM handling before NumPy, OpenCV and argparse load."""
    code = "import sys, kalmansfm.cli.main; print(sorted(m for m in ('numpy', 'cv2', 'argparse', 'kalmansfm.io') if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            env={"PYTHONPATH": str(SRC), "PATH": ""})
    assert result.stdout.strip() == "[]"


def test_every_public_name_loads_on_first_use():
    import kalmansfm

    assert all(getattr(kalmansfm, name) is not None for name in kalmansfm.__all__)
    assert set(kalmansfm.__all__) <= set(dir(kalmansfm))


def test_fuse_records_its_two_inputs_and_replaces_an_earlier_run_whole(tmp_path):
    scene = known_camera_scene(points=30, views=4, seed=0)
    frames = np.arange(4)
    (tmp_path / "cameras.csv").write_text(cameras_csv(CameraSet(scene.cameras.matrices, frames)))
    (tmp_path / "tracks.csv").write_text(observations_csv(scene.observations, frames, np.arange(30)))
    out = tmp_path / "fused"
    inputs = [str(tmp_path / "tracks.csv"), "--cameras", str(tmp_path / "cameras.csv"), "--out", str(out)]
    _run("fuse", *inputs)
    assert (out / "fusion.png").exists()
    _run("fuse", *inputs, "--no-plot", "--method", "batch")
    assert not (out / "fusion.png").exists()
    _owns_exactly_its_files(out)
    source = read_summary(out / "summary.json").source
    assert source.input == str((tmp_path / "tracks.csv").resolve()) and source.files == 2
    options = dict(source.options)
    assert options["plot"] == "false" and '"method":"batch"' in options["settings"]


def test_a_perspective_reconstruct_over_an_affine_one_records_the_intrinsics_and_leaves_no_motion(tmp_path):
    scene = perspective_scene(frames=5, points=60, pixel_std=0.5, seed=4)
    frames = np.arange(5)
    (tmp_path / "tracks.csv").write_text(observations_csv(scene.observations, frames, np.arange(60)))
    (tmp_path / "K.csv").write_text(intrinsics_csv(frames, scene.intrinsics))
    out = tmp_path / "shape"
    _run("reconstruct", str(tmp_path / "tracks.csv"), "--out", str(out), "--no-plot")
    assert (out / "motion.csv").exists()
    _run("reconstruct", str(tmp_path / "tracks.csv"), "--out", str(out), "--no-plot", "--camera", "perspective",
         "--intrinsics", str(tmp_path / "K.csv"))
    assert (out / "cameras.csv").exists() and not (out / "motion.csv").exists()
    _owns_exactly_its_files(out)
    source = read_summary(out / "summary.json").source
    assert source.files == 2  # the tracks and K.csv
    options = dict(source.options)
    camera = json.loads(options["camera"])
    assert camera["model"] == "perspective" and camera["intrinsics"].endswith("K.csv")
    assert camera["settings"]["method"] == "batch"


def test_a_long_sequence_keeps_its_frames_as_one_video_and_the_report_reads_it(tmp_path):
    """Issue 29: a long clip's run folder holds its frames as one video, not a PNG per frame."""
    from kalmansfm.io import load_run
    from kalmansfm.io.frames import MAX_PNG_FRAMES

    out = tmp_path / "long"
    frames = MAX_PNG_FRAMES + 5
    _run("demo", "--out", str(out), "--frames", str(frames))
    summary = read_summary(out / "summary.json")
    assert "frames.mp4" in summary.files and not any(name.startswith("frames/") for name in summary.files)
    assert not (out / "frames").exists()
    run = load_run(out)
    images = run.read_frames()
    assert len(images) == frames and images[0].shape == (240, 320)
    # H.264 at quality 18: within a few grey levels (the scene carries 2 levels of pixel noise, which it smooths)
    from kalmansfm.scenes import render_scene

    again = render_scene(n_frames=frames)
    assert np.abs(images[7].astype(int) - again.frames[7].astype(int)).mean() < 3.0
    html = (out / "report.html").read_text()
    assert f"of the {frames} frames, evenly spaced" in html or html.count('"frame":') == frames


def _video(path: Path, frames: list[np.ndarray], codec: str) -> Path:
    import cv2

    height, width = frames[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 25, (width, height), isColor=False)
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def test_a_long_clip_from_a_compressed_video_keeps_a_copy_of_it_and_a_raw_one_is_encoded(tmp_path):
    """Issue 29: a compressed input video is kept as it is (no time spent encoding, the frames bit for bit);
    one that holds many bits per pixel (motion JPEG here) is encoded into frames.mp4 instead."""
    from kalmansfm.io import load_run
    from kalmansfm.io.frames import MAX_COPIED_BITS_PER_PIXEL, MAX_PNG_FRAMES, encode_video, read_frames
    from kalmansfm.scenes import render_scene

    scene = render_scene(n_frames=MAX_PNG_FRAMES + 5)
    frames = [np.asarray(f) for f in scene.frames]
    compressed = tmp_path / "clip.mp4"
    compressed.write_bytes(encode_video(frames))
    raw = _video(tmp_path / "clip.avi", frames, "MJPG")
    pixels = sum(f.size for f in frames)
    assert 8 * compressed.stat().st_size <= MAX_COPIED_BITS_PER_PIXEL * pixels < 8 * raw.stat().st_size

    out = tmp_path / "copied"
    _run("demo", "--input", str(compressed), "--out", str(out))
    assert (out / "frames.mp4").read_bytes() == compressed.read_bytes()
    decoded = list(read_frames(compressed))
    kept = load_run(out).read_frames()
    assert len(kept) == len(decoded) and all(np.array_equal(a, b) for a, b in zip(kept, decoded))

    out = tmp_path / "encoded"
    _run("demo", "--input", str(raw), "--out", str(out))
    summary = read_summary(out / "summary.json")
    assert "frames.mp4" in summary.files and not (out / "frames.avi").exists()
    assert (out / "frames.mp4").stat().st_size < raw.stat().st_size
    assert len(load_run(out).read_frames()) == len(frames)
