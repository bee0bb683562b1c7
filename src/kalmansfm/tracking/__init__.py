"""Image tracking: corner detection, gated template search and the Kalman tracker."""
