"""Structure: factorization (shape and motion) and triangulation with known motion."""
