"""Pose conventions (chic_register.model.pose): slice angles and the trust check's depth."""

import numpy as np

from chic_register.model.pose import rigid, slice_angles, slice_frame


def test_slice_depth_is_slice_angles_depth():
    """The trust check's depth alone (slice_depth_mm) is slice_angles' depth bit for bit, normals up or down,
    NaN for a plane parallel to the axis."""
    from chic_register.model.pose import slice_depth_mm

    rng = np.random.default_rng(3)
    for _ in range(500):
        T = slice_frame(rng.uniform(0, 60), rng.uniform(0, 89), rng.uniform(-180, 180), rng.uniform(-180, 180))
        if rng.random() < 0.5:
            T = T @ rigid(np.diag([1.0, -1.0, -1.0]), np.zeros(3))  # the same plane, its normal down
        T[:3, 3] += rng.normal(size=3) * 5 * np.array([1, 1, 0]) @ T[:3, :3].T
        want = slice_angles(T).depth_mm
        assert slice_depth_mm(T) == want or (np.isnan(want) and np.isnan(slice_depth_mm(T)))
    assert np.isnan(slice_depth_mm(slice_frame(10.0, 90.0, 0.0, 0.0)))
