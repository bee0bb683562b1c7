"""tracks.csv writes every number by one rule: 6 decimals, trailing zeros and a bare point dropped, empty if not
finite.  The writer rewrites a whole text at once; here each field is checked against the rule applied alone."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.io.tracks import tracks_to_csv
from kalmansfm.tracking.tracks import Tracks, TrackStatus

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.floats(min_value=-1e4, max_value=1e4),
    st.sampled_from([0.0, -0.0, 1e-7, -1e-7, 5e-7, 100.0, 0.5, 123456789.123, 1e300, np.nan, np.inf, -np.inf]),
)


def _by_the_rule(value: float) -> str:
    return "" if not np.isfinite(value) else f"{value:.6f}".rstrip("0").rstrip(".")


@settings(max_examples=60, deadline=None)
@given(st.lists(st.lists(numbers, min_size=6, max_size=6), min_size=1, max_size=12),
       st.lists(st.sampled_from([TrackStatus.MEASURED, TrackStatus.PREDICTED, TrackStatus.LOST]), min_size=12,
                max_size=12))
def test_every_number_is_written_by_the_rule(rows, statuses):
    """Each field by the rule; a lost row (written by a format of its own) has every value field empty."""
    values = np.array(rows, dtype=np.float64)
    tracks = Tracks.empty(len(rows), 1)
    tracks.status[:, 0] = statuses[: len(rows)]
    tracks.states[:, 0] = values[:, :4]
    with np.errstate(over="ignore"):  # a standard deviation beyond 1e154 has an infinite variance: written empty
        variances = values[:, 4:] ** 2
    tracks.covariances[:, 0] = 0.0
    tracks.covariances[:, 0, 0, 0] = variances[:, 0]
    tracks.covariances[:, 0, 1, 1] = variances[:, 1]
    lines = tracks_to_csv(tracks).splitlines()[1:]
    assert len(lines) == len(rows)
    for line, state, position_std, status in zip(lines, values[:, :4], tracks.position_std[:, 0], statuses):
        fields = line.split(",")
        lost = status == TrackStatus.LOST
        assert fields[2:8] == ([""] * 6 if lost else [_by_the_rule(v) for v in (*state, *position_std)])
        assert fields[8] == status.label
