"""history.csv: every number written as the shortest text that reads back the same float, empty where none."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from kalmansfm.io._csv import CSV_CHUNK_ROWS, number
from kalmansfm.io.fusion import HISTORY_COLUMNS, history_csv_chunks
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.fusion import fuse


def test_every_number_is_written_by_the_rule_and_reads_back_the_same(monkeypatch):
    monkeypatch.setattr("kalmansfm.io.fusion.CSV_CHUNK_ROWS", 97)  # several pieces
    scene = known_camera_scene(points=60, views=6, outlier_fraction=0.05, seed=4)
    fused = fuse(scene.observations, scene.cameras, history=True)
    history = fused.details.history
    estimates = history.estimates.copy()
    estimates[::7, 1] = np.nan  # depth not determined yet: no value
    estimates[3, 2] = -0.0
    estimates[5, 0] = 1e-300
    fused = replace(fused, details=replace(fused.details, history=replace(history, estimates=estimates)))
    pieces = list(history_csv_chunks(fused))
    assert len(pieces) == 1 + -(-len(history) // 97) and CSV_CHUNK_ROWS > 97
    lines = "".join(pieces).splitlines()
    assert lines[0] == ",".join(HISTORY_COLUMNS) and len(lines) == len(history) + 1
    cov = history.covariances[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    for line, x, c in zip(lines[1:], estimates, cov):
        fields = line.split(",")
        assert fields[2:] == [number(v) for v in (*x, *c)]
        assert all(float(f) == v for f, v in zip(fields[2:], (*x, *c)) if f)
