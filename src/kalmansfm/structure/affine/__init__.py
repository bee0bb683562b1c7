"""Affine (orthographic) cameras: Tomasi–Kanade factorization with the metric upgrade, its
fast rank-3 subspace, and each recovered point's covariance."""
