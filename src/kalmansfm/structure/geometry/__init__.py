"""Camera geometry shared by every reconstruction: pinhole cameras (projection, linear
triangulation, per-point refinement, K R t from P), rotations as vectors, similarity
alignment, the rotations of orthographic camera rows, and two-view midpoint triangulation
with known motion."""
