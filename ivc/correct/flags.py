"""The per-sample flags of a correction (bits; 0 means the pose is trusted), in a module of their own so
that the compiled kernels can use them without importing the solver."""

OUTSIDE, NOT_CONVERGED, HIGH_RESIDUAL, INVALID_INPUT, LOW_PRECISION = 1, 2, 4, 8, 16
