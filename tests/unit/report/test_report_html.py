import json
import re

import numpy as np
import pytest
from fake_run import N_FRAMES, TRACK_IDS, drop_files, write_fake_run
from report_checks import assert_self_contained, decode_image_data_uri

from kalmansfm import InvalidInputError
from kalmansfm.io import RunSummary, load_run, summary_json
from kalmansfm.io.structure import CameraMotion
from kalmansfm.report import build_report
from kalmansfm.report.drawing import gate_ellipses, render_tracked_frames
from kalmansfm.report.figures import camera_rotations, survival_figure
from kalmansfm.tracking import TrackerSettings, Tracks

_SUMMARY = summary_json(RunSummary(command="demo", input="x")).replace("\n", "")

ALL_SECTIONS = [
    "sequence",
    "uncertainty",
    "tracks",
    "reconstruction",
    "shape",
    "motion",
    "ground-truth",
    "tables",
    "parameters",
    "files",
]


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    run = write_fake_run(tmp_path_factory.mktemp("full") / "run")
    path = build_report(run)
    return path, path.read_text(encoding="utf-8")


def test_full_run_has_every_section_and_is_self_contained(full_report):
    path, document = full_report
    assert path.name == "report.html"
    parsed = assert_self_contained(document)
    assert parsed.section_ids == ALL_SECTIONS
    assert {"player-image", "player-frames", "view3d", "shape-data", "js-status"} <= parsed.ids
    # strip of 6 frames + player + covariance trace, status, survival, singular values, 2 shape views,
    # rotation, tracking error, rotation error
    assert len(parsed.images) == 6 + 1 + 9
    assert not list(path.parent.glob(".*.tmp")), "temporary files left behind"


def test_player_carries_every_frame_and_frames_are_drawn_enlarged(full_report):
    _, document = full_report
    payload = re.search(r'<script type="application/json" id="player-frames">(.*?)</script>', document, re.S)
    frames = json.loads(payload.group(1))
    assert [f["frame"] for f in frames] == list(range(N_FRAMES))
    first = decode_image_data_uri(frames[0]["src"])
    # 64 x 48 frames are enlarged by an integer factor (560 px / 64 px -> 9) for display, with colour overlays
    assert first.shape == (48 * 9, 64 * 9, 3)
    assert (np.ptp(first.astype(int), axis=2) > 60).any(), "no coloured overlay drawn"


def test_header_values_are_escaped_and_numbers_shown(full_report):
    _, document = full_report
    assert "a&lt;b &amp; c" in document and "a<b & c" not in document
    assert "built-in scene (seed 0)" in document
    assert "window" in document and "gate_probability" in document and "gate radius c (used)" in document
    assert "0.41 px" in document  # residual card
    assert "track 4 was lost in frame 6" in document  # factorization warning


def test_shape_payload_holds_points_truth_and_cameras(full_report):
    _, document = full_report
    payload = json.loads(re.search(r'id="shape-data">(.*?)</script>', document, re.S).group(1))
    points = np.array(payload["points"])
    assert points.shape == (len(TRACK_IDS), 3)
    np.testing.assert_allclose(np.median(points, axis=0), 0, atol=1e-5)  # centred on the median (robust)
    assert np.array(payload["truth"]).shape == points.shape
    cameras = np.array(payload["cameras"])
    assert cameras.shape == (N_FRAMES, 3, 3)
    np.testing.assert_allclose(cameras @ np.swapaxes(cameras, 1, 2), np.broadcast_to(np.eye(3), cameras.shape), atol=1e-5)


def test_summary_only_gives_just_the_header_and_parameters(tmp_path):
    summary = RunSummary(command="track", input="x.mp4", settings=TrackerSettings(window=9))
    (tmp_path / "summary.json").write_text(summary_json(summary))
    parsed = assert_self_contained(build_report(tmp_path).read_text())
    assert parsed.section_ids == ["parameters"]
    assert parsed.images == []


def test_optional_inputs_missing_omit_their_sections(tmp_path):
    run = write_fake_run(tmp_path / "run", ground_truth=False, frames=False, prerendered=True, tables=False)
    document = build_report(run, out_name="other.html").read_text()
    parsed = assert_self_contained(document)
    assert "ground-truth" not in parsed.section_ids and "tables" not in parsed.section_ids
    assert "sequence" in parsed.section_ids  # tracks drawn on a plain canvas
    assert "No frame images in this run" in document
    assert "Covariance trace per frame (from the run)" in document
    assert "Recovered structure (from the run)" in document
    assert not (run / "report.html").exists()


def test_frames_without_tracks_show_the_raw_strip(tmp_path):
    run = write_fake_run(tmp_path / "run")
    drop_files(run, "tracks.npz", "structure.csv", "motion.csv")
    parsed = assert_self_contained(build_report(run).read_text())
    assert parsed.section_ids[0] == "sequence" and "parameters" in parsed.section_ids
    assert "shape" not in parsed.section_ids and "motion" not in parsed.section_ids


@pytest.mark.parametrize(
    "content, expected",
    [
        (None, r"summary\.json: not found"),
        ("{not json", r"summary\.json: line 1: not valid JSON \(column "),
        ("[1, 2]", r"summary\.json: expected a JSON object"),
        ('{"command": "demo"}', r"summary\.json: schema_version None is not 4"),
        (_SUMMARY[:-1] + ', "tracking": [1]}', r"summary\.json\.tracking: expected an object"),
        (_SUMMARY[:-1] + ', "files": ["a.csv", 3]}', r"summary\.json\.files\[1\]: expected a string"),
        (_SUMMARY[:-1] + ', "colour": "red"}', r"summary\.json: unknown field\(s\) colour"),
        (_SUMMARY[:-1] + ', "files": ["tracks.npz"]}', r"lists tracks\.npz, which is missing"),
    ],
)
def test_bad_summary_raises_naming_the_file(tmp_path, content, expected):
    if content is not None:
        (tmp_path / "summary.json").write_text(content)
    with pytest.raises(InvalidInputError, match=expected):
        build_report(tmp_path)
    assert not (tmp_path / "report.html").exists()


def test_missing_run_folder_is_an_input_error(tmp_path):
    with pytest.raises(InvalidInputError, match="does not exist"):
        build_report(tmp_path / "nowhere")


def test_out_name_must_be_a_file_name(tmp_path):
    write_fake_run(tmp_path)
    with pytest.raises(InvalidInputError, match="out_name"):
        build_report(tmp_path, out_name="../escape.html")


def _tracks_and_frames_only(run):
    """Drop the files whose sections need Matplotlib figures, to keep a test quick."""
    drop_files(run, "structure.csv", "motion.csv", "ground_truth_tracks.csv", "ground_truth_points.csv")
    summary = load_run(run).summary
    (run / "summary.json").write_text(summary_json(RunSummary(command="demo", input="fake", files=summary.files)))
    return run


def test_broken_optional_file_raises_and_keeps_the_old_report(tmp_path):
    run = _tracks_and_frames_only(write_fake_run(tmp_path / "run"))
    old = build_report(run).read_text()
    np.savez(run / "tracks.npz", positions=np.zeros((3, 2)), status=np.zeros(3), track_ids=np.zeros(3))
    with pytest.raises(InvalidInputError, match=r"tracks\.npz: positions must be a numeric \(frames, points, 2\) array"):
        build_report(run)
    assert (run / "report.html").read_text() == old


def test_bad_csv_row_names_file_and_line(tmp_path):
    run = write_fake_run(tmp_path / "run")
    (run / "structure.csv").write_text("track_id,X,Y,Z\n0,1,2,3\n1,1,oops,3\n")
    with pytest.raises(InvalidInputError, match=r"structure\.csv: line 3: column 'Y' must be a number"):
        load_run(run)
    (run / "structure.csv").write_text("id,X,Y\n")
    with pytest.raises(InvalidInputError, match=r"structure\.csv: line 1: missing column\(s\) track_id, Z"):
        load_run(run)


def test_ground_truth_tracks_are_matched_by_track_id(tmp_path):
    run = load_run(write_fake_run(tmp_path / "run"))
    truth = run.ground_truth_tracks
    assert truth.shape == run.tracks.positions.shape
    assert np.isnan(truth[3, 3]).all()  # not visible in frame 3
    assert np.isfinite(np.delete(truth.reshape(-1, 2), 3 * len(TRACK_IDS) + 3, axis=0)).all()


# --- figures -------------------------------------------------------------------------------


def test_gate_ellipse_of_correlated_covariance():
    covariance = np.array([[5.0, 3.0], [3.0, 5.0]])  # eigenvalues 8 along (1, 1) and 2 along (1, -1)
    axes, angle = gate_ellipses(covariance, TrackerSettings().effective_gate_radius)
    chi2_95 = 5.991464547107979
    np.testing.assert_allclose(axes, np.sqrt(chi2_95 * np.array([8.0, 2.0])), rtol=1e-12)
    assert angle == pytest.approx(45.0)


def test_drawn_gate_passes_through_its_semi_axes():
    sigma_x, sigma_y = 4.0, 2.0
    covariance = np.zeros((1, 1, 4, 4))
    covariance[0, 0] = np.diag([sigma_x**2, sigma_y**2, 1.0, 1.0])
    tracks = Tracks(
        positions=np.array([[[50.0, 40.0]]]),
        status=np.array([[1]]),
        track_ids=np.array([7]),
        covariances=covariance,
    )
    frame = np.zeros((100, 100), np.uint8)
    (image,) = render_tracked_frames([frame], tracks, [0], target_width=100)
    assert image.shape == (100, 100, 3)
    drawn = image.max(axis=2) > 40
    a, b = np.sqrt(5.991464547107979) * np.array([sigma_x, sigma_y])  # 9.79, 4.90 px
    assert drawn[40, int(round(50 + a))] and drawn[40, int(round(50 - a))]
    assert drawn[int(round(40 + b)), 50] and drawn[int(round(40 - b)), 50]
    assert not drawn[40, 50 + 7] and not drawn[40, 50 + 13]  # inside and outside the ring, off the marker
    assert drawn[40, 50]  # the measured point itself


def test_camera_rotations_recover_a_pure_pan():
    pans = np.radians(np.arange(6) * 4.0)
    c, s = np.cos(pans), np.sin(pans)
    zeros, ones = np.zeros(6), np.ones(6)
    motion = CameraMotion(
        frames=np.arange(6),
        i_rows=2.0 * np.column_stack([c, zeros, s]),  # scaled rows: the scale must not matter
        j_rows=2.0 * np.column_stack([zeros, ones, zeros]),
        translations=np.zeros((6, 2)),
    )
    angles, total = camera_rotations(motion)
    np.testing.assert_allclose(angles[:, 1], np.arange(6) * 4.0, atol=1e-9)
    np.testing.assert_allclose(angles[:, [0, 2]], 0.0, atol=1e-9)
    np.testing.assert_allclose(total, np.arange(6) * 4.0, atol=1e-9)


def test_player_is_subsampled_to_stay_within_its_size_budget(tmp_path, monkeypatch):
    import kalmansfm.report.html as report_html

    run = _tracks_and_frames_only(write_fake_run(tmp_path / "run"))
    one_frame = len(json.loads(re.search(r'id="player-frames">(.*?)</script>', build_report(run).read_text(), re.S)
                               .group(1))[0]["src"])
    monkeypatch.setattr(report_html, "MAX_PLAYER_BYTES", int(3.5 * one_frame))  # frame sizes differ a little
    document = build_report(run).read_text()
    frames = json.loads(re.search(r'id="player-frames">(.*?)</script>', document, re.S).group(1))
    assert [f["frame"] for f in frames] == [0, 4, 7]
    assert "3 of the 8 frames, evenly spaced" in document  # the player says it shows a subset


def test_shape_view_keeps_track_colours_and_truth_order_when_rows_are_shuffled(tmp_path):
    run = write_fake_run(tmp_path / "run")
    lines = (run / "structure.csv").read_text().splitlines()
    (run / "structure.csv").write_text("\n".join([lines[0], *reversed(lines[1:])]) + "\n")
    document = build_report(run).read_text()
    payload = json.loads(re.search(r'id="shape-data">(.*?)</script>', document, re.S).group(1))
    assert payload["labels"] == list(reversed(TRACK_IDS.tolist()))
    expected_colours = dict(zip(TRACK_IDS.tolist(), ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd"]))
    assert payload["colors"] == [expected_colours[t] for t in payload["labels"]]
    # the aligned truth of each point lies next to it (recovered = 14 x truth + 0.2 px noise)
    distances = np.linalg.norm(np.array(payload["truth"]) - np.array(payload["points"]), axis=1)
    assert distances.max() < 1.0


def test_unrecovered_points_and_degenerate_camera_rows_are_left_out(tmp_path):
    run = write_fake_run(tmp_path / "run")
    with (run / "structure.csv").open("a") as handle:
        handle.write("9,nan,nan,nan\n")
    with (run / "motion.csv").open("a") as handle:
        handle.write("8,0,0,0,0,0,0,32,24\n")
    document = build_report(run).read_text()
    assert_self_contained(document)
    payload = re.search(r'id="shape-data">(.*?)</script>', document, re.S).group(1)

    def reject(constant):
        raise AssertionError(f"{constant} in the 3D view's JSON")

    shape = json.loads(payload, parse_constant=reject)
    assert shape["labels"] == TRACK_IDS.tolist()
    assert shape["camera_frames"] == list(range(N_FRAMES))


def test_survival_figure_draws_the_tracks_it_is_given():
    status = np.array([[1, 1, 1], [1, 2, 1], [1, 3, 1], [1, 0, 2]], np.int8)
    positions = np.where((status == 1)[..., None] | (status == 2)[..., None], 10.0, np.nan) * np.ones((4, 3, 2))
    png = survival_figure(Tracks(positions=positions, status=status, track_ids=np.arange(3)))
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert survival_figure(Tracks(positions=np.zeros((4, 0, 2)), status=np.zeros((4, 0), np.int8), track_ids=np.zeros(0, np.int64))) is None


def test_a_frame_list_warning_names_the_first_frames_and_says_when_there_are_more():
    from kalmansfm.report.markup import frames_warning as _frames_warning

    assert _frames_warning("Frames <x>", [3, 4], 2) == '<p class="warn">Frames &lt;x&gt;: 3, 4</p>'
    assert _frames_warning("Frames", list(range(15)), 12).endswith(": 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11 …</p>")
