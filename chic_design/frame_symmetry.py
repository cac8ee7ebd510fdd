"""Symmetries of a fiducial in 3-D: see :mod:`chic_register.model.symmetry` (the solver refuses a self-symmetric
frame without a prior by the same test; the code lives there, once)."""

from chic_register.model.symmetry import (  # noqa: F401
    FrameSymmetry,
    candidate_rotations,
    frame_symmetries,
    rotation_mismatch,
)
