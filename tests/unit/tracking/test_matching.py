"""Gate geometry, template search and sub-pixel accuracy of the matcher."""

import cv2
import numpy as np
import pytest
from scipy.stats import chi2

from kalmansfm.errors import InvalidInputError
from kalmansfm.tracking.matching import (
    match_templates,
    prepare_frame,
    refine_translation,
    sample_patches,
    subpixel_peak,
)
from kalmansfm.tracking.settings import gate_radius_for_probability


def textured(shape, seed, blur=1.5):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, shape), (0, 0), blur)


def test_gate_radius_is_chi_square_quantile():
    for p in (0.5, 0.9, 0.95, 0.99):
        assert gate_radius_for_probability(p) ** 2 == pytest.approx(chi2.ppf(p, 2))
        # 2-dof closed form: c² = -2 ln(1 - p)
        assert gate_radius_for_probability(p) ** 2 == pytest.approx(-2 * np.log(1 - p))
    with pytest.raises(InvalidInputError, match="gate probability"):
        gate_radius_for_probability(1.0)


@pytest.mark.parametrize(
    ("offset", "inside"),
    # Σ with axes 3 (along 30°) and 1 (across), c = 2: squared Mahalanobis distances 3.79, 3.11, 3.79 inside;
    # 5.14, 4.98, 12.9 outside.
    [((5, 3), True), ((0, 2), True), ((-5, -3), True), ((6, 3), False), ((-1, 2), False), ((2, -3), False)],
)
def test_search_finds_the_template_exactly_inside_a_rotated_gate(offset, inside):
    angle = np.radians(30)
    u = np.array([np.cos(angle), np.sin(angle)])
    v = np.array([-u[1], u[0]])
    cov = 9 * np.outer(u, u) + 1 * np.outer(v, v)
    img = textured((90, 110), seed=3)
    predicted = np.array([55.0, 45.0])
    true = predicted + np.array(offset, float)
    template = sample_patches(img, true[None], 11)
    match = match_templates(prepare_frame(img, 11, 20), template, predicted[None], cov[None], 2.0)
    # the integer candidate is exact; its sub-pixel fit may lean a little where the 3×3 neighbourhood meets the gate
    found_there = np.linalg.norm(match.positions[0] - true) < 0.25 and match.dissimilarity[0] < 1e-6
    assert found_there == inside


def test_search_respects_the_gate():
    img = textured((80, 100), seed=1)
    template = sample_patches(img, np.array([[50.0, 40.0]]), 11)
    frame = prepare_frame(img, 11, 20)
    # True position 6 px right of the prediction: found with σ = 3, c = 2.45 (radius 7.3) ...
    wide = match_templates(frame, template, np.array([[44.0, 40.0]]), np.eye(2)[None] * 9, 2.45)
    np.testing.assert_allclose(wide.positions, [[50.0, 40.0]], atol=0.05)
    assert wide.dissimilarity[0] < 1e-6
    # ... but not with σ = 1 (radius 2.45): the best candidate inside the gate is a poor match.
    narrow = match_templates(frame, template, np.array([[44.0, 40.0]]), np.eye(2)[None], 2.45)
    assert np.linalg.norm(narrow.positions[0] - [44.0, 40.0]) <= 2.45 + 0.5
    assert narrow.dissimilarity[0] > 0.5


def test_search_clips_the_gate_to_the_image_and_reports_unsearchable_tracks():
    img = textured((60, 60), seed=2)
    templates = sample_patches(img, np.array([[30.0, 30.0], [30.0, 30.0]]), 11)
    frame = prepare_frame(img, 11, 20)
    predicted = np.array([[2.0, 30.0], [-30.0, 30.0]])  # near the border; off the image
    m = match_templates(frame, templates, predicted, np.eye(2)[None].repeat(2, 0) * 25, 2.45)
    assert m.searched.tolist() == [True, False]
    assert m.positions[0, 0] >= 5  # no candidate whose window leaves the image
    assert np.isnan(m.positions[1]).all()


@pytest.mark.parametrize("score", ["ssd", "ncc"])
def test_subpixel_shift_recovered_within_a_tenth_of_a_pixel(score):
    rng = np.random.default_rng(7)
    img = textured((90, 90), seed=3, blur=2.0)
    frame = prepare_frame(img, 11, 10)
    truth = np.array([[45.0, 45.0]]) + rng.uniform(-0.5, 0.5, (1, 2))
    # The template is the pattern seen at a sub-pixel position; the search starts 3 px off.
    template = sample_patches(img, truth, 11)
    m = match_templates(frame, template, truth + [[3.0, -2.0]], np.eye(2)[None] * 16, 2.45, score=score)
    assert np.abs(m.positions - truth).max() <= 0.25  # integer search + quadratic fit
    refined = refine_translation(img, template, m.positions)
    assert np.abs(refined - truth).max() <= 0.1


def test_subpixel_on_a_shifted_image():
    img = textured((90, 90), seed=4, blur=2.0)
    shift = (0.37, -0.21)
    moved = cv2.warpAffine(img, np.float64([[1, 0, shift[0]], [0, 1, shift[1]]]), (90, 90), flags=cv2.INTER_CUBIC)
    template = img[40:51, 40:51].copy()  # centred on (45, 45)
    m = match_templates(prepare_frame(moved, 11, 8), template[None], np.array([[45.0, 45.0]]), np.eye(2)[None] * 4, 2.45)
    refined = refine_translation(moved, template[None], m.positions)
    np.testing.assert_allclose(refined, [[45 + shift[0], 45 + shift[1]]], atol=0.1)


def test_subpixel_peak_of_an_exact_quadratic():
    y, x = np.mgrid[-1:2, -1:2]
    cost = 2 * (x - 0.25) ** 2 + (x - 0.25) * (y - 0.1) + 3 * (y - 0.1) ** 2
    np.testing.assert_allclose(subpixel_peak(cost[None].astype(float)), [[0.25, 0.1]], atol=1e-12)
