"""The whole job on the built-in scene: frames → tracks → structure → report, checked against ground truth."""

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import RunSummary, read_summary, summary_json
from kalmansfm.pipeline import DemoRequest, run_demo


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    return run_demo(DemoRequest(tmp_path_factory.mktemp("demo") / "run", seed=0, html=False))


def test_demo_writes_every_output_file(demo_run):
    names = {p.name for p in demo_run.out_dir.iterdir()}
    expected = {
        "tracks.csv", "tracks.npz", "covariance_trace.png", "tracks.png", "structure.csv", "structure.ply",
        "structure.png", "motion.csv", "summary.json", "ground_truth_tracks.csv", "ground_truth_points.csv",
        "frames",
    }
    assert expected <= names
    assert len(list((demo_run.out_dir / "frames").glob("frame_*.png"))) == 30
    assert not [n for n in names if n.endswith(".tmp")]


def test_demo_meets_the_tracking_and_shape_targets(demo_run):
    """Issue targets on the built-in scene: RMS ≤ 0.5 px, ≥ 97 % within 2 px, shape error ≤ 2 % of the radius."""
    truth = read_summary(demo_run.out_dir / "summary.json").truth
    assert truth is not None
    assert truth.tracking_rms_error_px <= 0.5
    assert truth.within_2px >= 0.97
    assert truth.shape_error_pct <= 2.0
    # the recovered cameras turn like the true ones (a few degrees at most)
    assert max(a for a in truth.rotation_error_deg if a is not None) < 5.0


def test_summary_matches_the_returned_objects(demo_run):
    s = demo_run.summary
    assert read_summary(demo_run.out_dir / "summary.json") == s
    assert s.tracking.tracks == demo_run.tracks.track_ids.size
    np.testing.assert_allclose(s.reconstruction.singular_values, demo_run.reconstruction.details.singular_values[:10])
    assert len(s.tracking.per_track) == demo_run.tracks.track_ids.size


def test_tracking_error_is_counted_once_over_the_measured_visible_estimates(demo_run):
    """The summary's error figures come from one population; the report shows them, it does not recount."""
    truth = demo_run.summary.truth
    scene = demo_run.scene
    tracks = demo_run.tracks
    true = scene.positions[:, np.searchsorted(scene.track_ids, tracks.track_ids)]
    visible = scene.visible[:, np.searchsorted(scene.track_ids, tracks.track_ids)]
    pick = tracks.measured & visible
    errors = np.linalg.norm(tracks.positions - true, axis=-1)
    assert truth.tracking_rms_error_px == pytest.approx(np.sqrt(np.mean(errors[pick] ** 2)), rel=1e-12)
    assert truth.median_error_px == pytest.approx(np.median(errors[pick]), rel=1e-12)
    assert truth.max_error_px == pytest.approx(errors[pick].max(), rel=1e-12)
    per_frame = [np.sqrt(np.mean(errors[f][pick[f]] ** 2)) if pick[f].any() else None for f in range(len(pick))]
    np.testing.assert_allclose(np.array(truth.rms_error_per_frame_px, dtype=float),
                               np.array(per_frame, dtype=float), rtol=1e-12)
    from kalmansfm.report import build_report

    html = build_report(demo_run.out_dir).read_text()
    assert f"<td class=\"num\" data-sort=\"{truth.max_error_px}\">{truth.max_error_px:.4g}</td>" in html


def test_demo_command_prints_the_summary_and_the_report_path(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "12", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "tracking:" in printed and "structure:" in printed and f"report: {out / 'report.html'}" in printed
    html = (out / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>") and "data:image/png;base64," in html


def test_demo_on_a_real_sequence_has_no_ground_truth_section(tmp_path, capsys):
    from pathlib import Path
    import shutil

    source = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "cmu_house" / "images"
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(8):
        shutil.copy(source / f"house.seq{k}.png", frames / f"house.seq{k}.png")
    assert main(["demo", "--input", str(frames), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    s = read_summary(tmp_path / "run" / "summary.json")
    assert s.truth is None
    assert s.tracking.tracks >= 20
    assert "within" not in capsys.readouterr().out


def test_a_failed_run_leaves_the_previous_results(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    previous = summary_json(RunSummary(command="demo", input="previous", files=("summary.json",)))
    (out / "summary.json").write_text(previous)
    assert main(["demo", "--input", str(tmp_path / "missing"), "--out", str(out), "--quiet"]) == 2
    assert (out / "summary.json").read_text() == previous
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "missing" in err
