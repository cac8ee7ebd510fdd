"""Pose conventions (chic_register.model.pose): slice angles, the trust check's depth, a pose near the prior."""

import numpy as np
import pytest

from chic_register.model.pose import near_prior, rigid, rot_y, rot_z, slice_angles, slice_frame
from chic_register.options import SolveOptions


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


def test_without_a_prior_every_pose_is_near_it():
    assert near_prior(rigid(rot_y(170.0), (5.0, 0.0, 0.0)), SolveOptions())


@pytest.mark.parametrize("turn_deg, limit_deg, near", [(50.0, 60.0, True), (50.0, 45.0, False), (-59.0, 60.0, True),
                                                       (61.0, 60.0, False)])
def test_a_pose_is_near_the_prior_within_its_angle(turn_deg, limit_deg, near):
    """The prior is the fiducial upright in the scanner (R_scanner_from_fiducial = I, 40 mm away: its translation is
    not compared); the pose (T_F_from_scanner) has the fiducial turned ``turn_deg`` about the scanner's z."""
    opts = SolveOptions(prior=rigid(np.eye(3), (0.0, 0.0, 40.0)), prior_max_deg=limit_deg)
    T_F_from_scanner = rigid(rot_z(-turn_deg), (3.0, -2.0, 0.0))
    assert near_prior(T_F_from_scanner, opts) is near
