"""NumPy references that only the tests use: each compiled kernel of the package is compared with one.

``decoupled``: the constant-velocity Kalman step, predict then update (``kalmansfm.estimation._kernels``);
``alignment``: the differential matcher's template alignment (``kalmansfm.tracking._align_kernel``).
The general dense Kalman kernels are compared with the public ``kalman_predict`` / ``kalman_update``.
"""
