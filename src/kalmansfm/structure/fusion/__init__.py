"""Structure fusion with known cameras: every point's 3-D position and covariance, view by
view (recursive inverse-depth Kalman updates), per-point maximum likelihood, or the report's
pair fusion; and Task 7's landmarks from a moving camera."""
