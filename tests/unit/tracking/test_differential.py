"""The differential measurement: alignment, anchors, checks and their rejection codes, and the noise it reports."""

import cv2
import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.tracking.differential import (
    ACCEPTED,
    APPEARANCE,
    FORWARD_BACKWARD,
    GATE,
    IMPLAUSIBLE,
    NOT_FOUND,
    OUTSIDE,
    REJECTION_NAMES,
    AnchorTemplates,
    DifferentialSettings,
    TrackPredictions,
    align_templates,
    measure_differential,
    prepare_differential_frame,
    pyramid_levels,
)
from reference.alignment import align_numpy, template_terms


def texture(seed=0, size=(160, 220), blur=2.0):
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.uniform(0, 255, size), (0, 0), blur)
    return (image - image.mean()) / image.std() * 35 + 128


def shifted(image, dx, dy):
    """``image`` moved by (dx, dy) px exactly (a phase ramp on its spectrum; the texture wraps)."""
    h, w = image.shape
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None, :]
    return np.fft.ifft2(np.fft.fft2(image) * np.exp(-2j * np.pi * (fx * dx + fy * dy))).real


GRID = np.stack(np.meshgrid(np.arange(40.0, 180.0, 14.0), np.arange(40.0, 120.0, 14.0)), -1).reshape(-1, 2)


def test_alignment_recovers_exact_sub_pixel_shifts():
    base = texture()
    a = prepare_differential_frame(base, 11)
    b = prepare_differential_frame(shifted(base, 0.37, -0.21), 11)
    alignment = align_templates(b, a.patches(GRID), GRID + [0.6, 0.3], iterations=4)
    error = alignment.positions - (GRID + [0.37, -0.21])
    # Bilinear sampling of template and patch at fractional offsets leaves a few hundredths of a pixel.
    assert np.sqrt(np.mean(np.sum(error**2, axis=1))) < 0.05
    assert alignment.converged.all() and (alignment.ncc > 0.99).all()
    assert (np.linalg.eigvalsh(alignment.covariances) > 0).all()


def test_alignment_ignores_brightness_and_contrast():
    base = texture(1)
    a = prepare_differential_frame(base, 11)
    b = prepare_differential_frame(0.6 * shifted(base, -0.5, 0.25) + 40.0, 11)
    alignment = align_templates(b, a.patches(GRID), GRID, iterations=4)
    error = np.linalg.norm(alignment.positions - (GRID + [-0.5, 0.25]), axis=1)
    assert np.sqrt(np.mean(error**2)) < 0.06 and error.max() < 0.2


def test_an_alignment_that_runs_away_keeps_its_start():
    flat = prepare_differential_frame(np.full((60, 60), 100.0), 11)
    start = np.array([[30.0, 30.0]])
    alignment = align_templates(flat, prepare_differential_frame(texture(2, (60, 60)), 11).patches(start), start, max_shift_px=0.5)
    np.testing.assert_array_equal(alignment.positions, start)


def test_anchor_bank_keeps_its_templates_through_take_replace_and_append():
    rng = np.random.default_rng(3)
    templates = rng.uniform(0, 255, (6, 11, 11)).astype(np.float32)
    new = rng.uniform(0, 255, (2, 11, 11)).astype(np.float32)
    bank = AnchorTemplates(templates).take(np.array([0, 2, 3, 5])).replace(np.array([1]), new[:1]).append(new[1:])
    expected = np.concatenate([templates[[0]], new[:1], templates[[3, 5]], new[1:]])
    np.testing.assert_array_equal(bank.templates, expected)
    assert bank.templates.dtype == np.float32 and bank.templates.flags.c_contiguous


def test_pyramid_depth_grows_with_the_reach():
    assert pyramid_levels(np.array([2.0, 6.0, 12.0, 30.0, 500.0]), max_level=3).tolist() == [0, 1, 2, 3, 3]
    assert pyramid_levels(np.array([500.0]), max_level=1).tolist() == [1]


def frames_and_anchors(step=(2.0, -1.0), seed=4):
    base = texture(seed)
    previous = prepare_differential_frame(np.clip(np.rint(base), 0, 255).astype(np.uint8), 11)
    current = prepare_differential_frame(np.clip(np.rint(shifted(base, *step)), 0, 255).astype(np.uint8), 11)
    return previous, current, previous.patches(GRID), AnchorTemplates(previous.patches(GRID))


def measure(previous, current, patches, anchors, predicted, covariance=4.0, **options):
    k = len(GRID)
    tracks = TrackPredictions(GRID, patches, predicted, np.broadcast_to(np.eye(2) * covariance, (k, 2, 2)), anchors, **options)
    return measure_differential(previous, current, tracks)


def test_a_clean_translation_is_measured_anchored_with_a_small_noise():
    previous, current, patches, anchors = frames_and_anchors()
    m = measure(previous, current, patches, anchors, GRID + [1.5, -0.5])
    assert (m.rejection == ACCEPTED).all() and m.accepted.all() and m.anchored.all()
    np.testing.assert_allclose(m.positions, GRID + [2.0, -1.0], atol=0.05)
    # R: the alignment's own σ² H⁻¹ plus the (0.12 px)² floor; it carries the rest on to the chain.
    stds = np.sqrt(np.diagonal(m.noise_covariances, axis1=1, axis2=2))
    assert ((stds >= 0.12) & (stds < 0.25)).all()
    assert (np.linalg.eigvalsh(m.carried_covariances) > 0).all()
    # The anchor matches very well where the flow ended: the flow back is not needed there.
    assert np.isnan(m.forward_backward_px).all()
    assert m.patches.shape == (len(GRID), 11, 11) and np.isfinite(m.patches).all()


def test_the_flow_back_is_checked_where_the_anchor_does_not_settle_the_match():
    previous, current, patches, _ = frames_and_anchors()
    # Anchors of a changed appearance (noisy): they no longer match very well, so the
    # chain measures, after the flow back from each match has landed where the track was.
    noisy = AnchorTemplates(patches + np.random.default_rng(5).normal(0.0, 10.0, patches.shape))
    m = measure(previous, current, patches, noisy, GRID + [1.5, -0.5])
    checked = np.isfinite(m.forward_backward_px)
    assert checked.mean() > 0.9 and (m.forward_backward_px[checked] < 0.1).all()
    assert not m.anchored[checked].any() and m.accepted[checked].all()
    np.testing.assert_allclose(m.positions[checked], GRID[checked] + [2.0, -1.0], atol=0.05)


def test_each_check_refuses_with_its_own_reason():
    previous, current, patches, anchors = frames_and_anchors()
    # A point predicted far away with a confident covariance: the flow from there finds
    # something else or nothing; whatever it finds lies outside the tight gate.
    far = measure(previous, current, patches, anchors, GRID + [9.0, 9.0], covariance=0.25)
    assert not far.accepted.any()
    assert set(far.rejection.tolist()) <= {GATE, FORWARD_BACKWARD, NOT_FOUND, APPEARANCE}
    # The plausible radius refuses a match the gate would take.
    tight = measure(previous, current, patches, anchors, GRID + [1.0, -1.0], max_innovation_px=np.full(len(GRID), 0.3))
    assert (tight.rejection == IMPLAUSIBLE).all()
    # Anchors of another texture: the appearance check refuses the matches (but for the odd
    # patch of the other texture that happens to look alike) ...
    other = prepare_differential_frame(texture(9), 11).patches(GRID)
    wrong = measure(previous, current, other, AnchorTemplates(other), GRID + [2.0, -1.0])
    assert np.mean(wrong.rejection == APPEARANCE) >= 0.95
    # ... unless the previous frame's patch matches cleanly (a mild appearance change that the
    # chain follows): then a match whose anchor still matches at rescue_ncc is taken, chained.
    mild = measure(previous, current, patches, AnchorTemplates(other), GRID + [2.0, -1.0])
    taken = mild.accepted
    assert np.mean(taken) <= 0.1 and (mild.anchor_ncc[taken] >= 0.7).all() and not mild.anchored[taken].any()
    assert (mild.rejection[~taken] == APPEARANCE).all()
    # Predictions off the image.
    gone = measure(previous, current, patches, anchors, GRID - [500.0, 0.0])
    assert (gone.rejection == OUTSIDE).all()
    assert set(REJECTION_NAMES) >= set(np.unique(np.concatenate([far.rejection, tight.rejection, wrong.rejection, gone.rejection])).tolist())


def test_a_coasting_track_is_found_again_by_its_anchor():
    previous, current, patches, anchors = frames_and_anchors(step=(3.0, 2.0))
    coasting = np.ones(len(GRID), bool)
    m = measure(previous, current, np.full_like(patches, np.nan), anchors, GRID + [2.0, 1.5], coasting=coasting)
    assert m.accepted.all() and (m.levels == -1).all()
    np.testing.assert_allclose(m.positions, GRID + [3.0, 2.0], atol=0.1)


def test_frames_of_different_sizes_and_misshaped_inputs_are_refused():
    previous, current, patches, anchors = frames_and_anchors()
    small = prepare_differential_frame(np.zeros((50, 50), np.uint8), 11)
    with pytest.raises(InvalidInputError, match="differ in size"):
        measure(previous, small, patches, anchors, GRID)
    with pytest.raises(InvalidInputError, match="one row per track"):
        TrackPredictions(GRID, patches[:3], GRID, np.zeros((len(GRID), 2, 2)), anchors)
    with pytest.raises(InvalidInputError, match="11×11 anchors"):
        small_anchors = AnchorTemplates(np.zeros((len(GRID), 7, 7)))
        measure_differential(previous, current, TrackPredictions(GRID, np.zeros((len(GRID), 7, 7)), GRID,
                                                                 np.zeros((len(GRID), 2, 2)), small_anchors))


def test_differential_settings_take_the_trackers_values_and_check_their_own():
    from kalmansfm.tracking import TrackerSettings

    tracker = TrackerSettings(window=15, gate_probability=0.99, min_ncc=0.85, max_pyramid_level=2)
    s = DifferentialSettings.from_tracker(tracker, rescue_ncc=0.65)
    assert (s.window, s.gate_radius, s.min_ncc, s.max_level, s.rescue_ncc) == (15, tracker.effective_gate_radius, 0.85, 2, 0.65)
    np.testing.assert_array_equal(np.asarray(s.fallback_noise), tracker.model.R)
    default = DifferentialSettings()  # the tracker's defaults, defined once in TrackerSettings
    assert (default.window, default.min_ncc, default.anchor_ncc, default.reacquire_ncc, default.forward_backward_px,
            default.max_level) == (11, 0.8, 0.97, 0.9, 1.0, 3)
    assert default.gate_radius == TrackerSettings().effective_gate_radius and default.fallback_noise is None
    for bad, message in ((dict(window=10), "window must be an odd integer"), (dict(min_ncc=0.0), "min_ncc must be"),
                         (dict(fallback_noise=((1.0, 2.0), (2.0, 1.0))), "fallback_noise must be a symmetric positive"),
                         (dict(max_level=-1), "max_level must be")):
        with pytest.raises(InvalidInputError, match=message):
            DifferentialSettings(**bad)


def test_settings_check_the_differential_options():
    from kalmansfm.tracking import TrackerSettings

    assert TrackerSettings().matcher == "differential" and TrackerSettings().coast_limit == 5
    assert TrackerSettings(matcher="search").coast_limit == 3 and TrackerSettings(max_misses=1).coast_limit == 1
    with pytest.raises(InvalidInputError, match="matcher must be one of"):
        TrackerSettings(matcher="nearest")
    with pytest.raises(InvalidInputError, match="min_ncc must be a correlation in"):
        TrackerSettings(min_ncc=1.5)
    with pytest.raises(InvalidInputError, match="forward_backward_px must be finite and > 0; got 0.0"):
        TrackerSettings(forward_backward_px=0.0)
    with pytest.raises(InvalidInputError, match="max_pyramid_level must be"):
        TrackerSettings(max_pyramid_level=-1)


@pytest.mark.parametrize("scale", [1.0 / 255.0, 257.0])
def test_frames_in_another_grey_range_are_tracked_as_well(scale):
    """0…1 floats and 16-bit frames: the flow sees them scaled to 8 bits once, by the first frame."""
    from kalmansfm.tracking import track

    base = texture(5)
    frames = [np.clip(shifted(base, 1.2 * k, -0.6 * k), 0, 255) for k in range(6)]
    start = GRID[:10]
    reference = track([np.rint(f).astype(np.uint8) for f in frames], start)
    other = track([f * scale if scale < 1 else (f * scale).astype(np.uint16) for f in frames], start)
    assert other.measured.all()  # measured (the first two frames: initialising)
    np.testing.assert_allclose(other.positions, reference.positions, atol=0.05)


@pytest.mark.parametrize("iterations", [0, 1, 3])
def test_the_compiled_alignment_matches_its_numpy_reference(iterations):
    from kalmansfm.tracking.alignment import _align_compiled

    rng = np.random.default_rng(6)
    base = texture(7)
    frame = prepare_differential_frame(0.8 * shifted(base, 1.3, -0.6) + rng.normal(0.0, 3.0, base.shape), 11)
    # Points in the middle, at the border (replicated edge), one far outside, one not finite.
    points = np.concatenate([GRID, [[0.5, 30.0], [219.0, 159.0], [-40.0, 10.0], [np.nan, 5.0]]])
    bank = AnchorTemplates(prepare_differential_frame(base, 11).patches(points))
    bank.templates[3] = 50.0  # a flat template: no step, NaN covariance
    start = points + rng.uniform(-1.0, 1.0, points.shape)
    compiled = _align_compiled(frame, bank, start, iterations, 1.5)
    reference = align_numpy(frame, AnchorTemplates(bank.templates), start, iterations, 1.5)
    np.testing.assert_array_equal(compiled.converged, reference.converged)
    for name, tolerance in (("positions", 1e-4), ("ncc", 1e-5), ("covariances", 1e-5), ("min_eigenvalue", 1e-4),
                            ("residual_variance", 1e-3), ("patches", 1e-3)):
        np.testing.assert_allclose(getattr(compiled, name), getattr(reference, name), rtol=1e-4, atol=tolerance, err_msg=name)


def test_one_well_posedness_test_for_the_numpy_paths_and_the_compiled_kernel():
    """matching.well_posed_2x2 decides for the NumPy reference; the kernel's inline copy agrees."""
    from kalmansfm.tracking.alignment import _align_compiled
    from kalmansfm.tracking.matching import well_posed_2x2

    r, c = np.mgrid[0:11, 0:11].astype(np.float32)
    rng = np.random.default_rng(3)
    templates = np.stack([
        np.full((11, 11), 80.0, np.float32),  # flat: H = 0
        100.0 * (c > 5),  # vertical edge: gy = 0, det = 0
        100.0 * (r > 5),  # horizontal edge
        100.0 * (r + c > 10),  # diagonal edge: gx = gy, det = 0 exactly
        100.0 * ((r > 5) & (c > 5)),  # corner: well posed
        rng.uniform(0, 255, (11, 11)),  # texture: well posed
    ]).astype(np.float32)
    terms = template_terms(templates)
    g = terms.gradients.astype(np.float64)
    det, expected = well_posed_2x2((g[:, 0] ** 2).sum(1), (g[:, 0] * g[:, 1]).sum(1), (g[:, 1] ** 2).sum(1))
    assert expected.tolist() == [False, False, False, False, True, True]
    assert terms.well_posed.tolist() == expected.tolist()
    frame_image = np.full((60, 60), 80.0)
    points = np.array([[30.0, 30.0]] * len(templates))
    for k, t in enumerate(templates):  # the frame shows each template where it is aligned (one at a time)
        image = frame_image.copy()
        image[25:36, 25:36] = t
        frame = prepare_differential_frame(image, 11)
        bank = AnchorTemplates(templates[k:k + 1])
        compiled = _align_compiled(frame, bank, points[k:k + 1], 2, 1.5)
        reference = align_numpy(frame, AnchorTemplates(templates[k:k + 1]), points[k:k + 1], 2, 1.5)
        assert np.isnan(compiled.covariances).all() == np.isnan(reference.covariances).all() == (not expected[k]), k
