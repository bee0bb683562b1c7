"""Golden: fusing the Oxford VGG data with their own cameras reproduces their own 3-D points.

The datasets' points are the maximum-likelihood points for their cameras, so the
fused structure must equal them (median difference <= 1e-4 of the object radius).
The files go through the documented converter (examples/oxford_to_csv.py) and the
project's readers, as a user's would.  Source: Visual Geometry Group, University of
Oxford, multi-view data (``../shared/data/oxford_model_house``, ``oxford_merton1``).
"""


import numpy as np
import pytest
from scipy import stats

from kalmansfm.io.cameras import match_cameras, read_cameras
from kalmansfm.io.tracks import read_tracks
from kalmansfm.structure.fusion import fuse

from _oxford import DATASETS, convert


@pytest.fixture(scope="module", params=DATASETS)
def dataset(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    convert(request.param, out)
    cams = read_cameras(out / "cameras.csv")
    tracks = read_tracks(out / "tracks.csv")
    matched = match_cameras(tracks.observations(), tracks.frames, tracks.track_ids, cams)
    reference = np.loadtxt(out / "points3d.csv", delimiter=",", skiprows=1)
    points = np.full((int(reference[:, 0].max()) + 1, 3), np.nan)
    points[reference[:, 0].astype(int)] = reference[:, 1:]
    return request.param, matched, points[matched.track_ids]


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_fused_points_are_the_datasets_own(dataset, method):
    name, matched, truth = dataset
    f = fuse(matched.observations, matched.cameras, method=method, history=True)
    assert f.reconstructed.all()
    radius = np.median(np.linalg.norm(truth - np.median(truth, axis=0), axis=1))
    difference = np.linalg.norm(f.points - truth, axis=1) / radius
    assert np.median(difference) <= 1e-4
    # plausible noise: the VGG readmes quote median reprojection errors of 0.1-0.4 px
    assert 0.1 < f.noise.std < 0.5
    if name == "oxford_model_house":
        assert f.details.orientation == -1  # the mirrored reconstruction: points at negative depth with det R = +1
        assert 40 <= f.observations.rejected_mask().sum() <= 150  # some gross mismatches


def test_two_view_estimates_agree_with_the_final_ones_within_their_own_covariance(dataset):
    """The difference of a nested estimate and the final one has covariance Σ_early - Σ_final.

    After one more view that difference has rank 2 (χ²(2)); after two or more, rank 3 (χ²(3)).
    """
    _, matched, _ = dataset
    f = fuse(matched.observations, matched.cameras, history=True)
    first = f.details.history.first()
    extra = f.views[first.points] - 2
    for more, dof in ((1, 2), (2, 3)):
        sel = np.isfinite(first.estimates).all(axis=1) & ((extra == 1) if more == 1 else (extra >= 2))
        if sel.sum() < 50:
            continue
        e = first.estimates[sel] - f.points[first.points[sel]]
        w, U = np.linalg.eigh(first.covariances[sel] - f.point_covariances[first.points[sel]])
        z = np.einsum("nij,ni->nj", U[:, :, -dof:], e)
        nees = np.sum(z**2 / w[:, -dof:], axis=1)
        assert 0.6 < np.median(nees) / stats.chi2.median(dof) < 1.3
