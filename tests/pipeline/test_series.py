"""Series: several slices registered jointly, slices of different poses refused, and a series deciding what one
slice cannot.
"""

import numpy as np
import pytest

from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import apply, invert, rigid, slice_frame
from chic_register.pipeline.register import register
from tests.conftest import ROOT


def _scanner_from_image_for(T_sf, depth, tilt, az, tw, shape=(256, 256), spacing=(0.5, 0.5)):
    """The image placement that makes a slice at these angles see the fiducial at ``T_sf``."""
    T_image_from_S = rigid(np.eye(3), ((shape[1] - 1) / 2 * spacing[1], (shape[0] - 1) / 2 * spacing[0], 0))
    return T_sf @ slice_frame(depth, tilt, az, tw) @ invert(T_image_from_S)


def test_joint_registration_of_several_slices(neuro_geometry):
    T_sf = rigid(slice_frame(0, 20, 30, 40)[:3, :3], (5.0, -3.0, 60.0))
    poses = [(15, 10, 0, 0), (25, 10, 0, 0), (35, 10, 0, 0)]
    sims = [simulate_slice(neuro_geometry, *p, noise="uniform", noise_level=0.1, rng=i,
                           T_scanner_from_image=_scanner_from_image_for(T_sf, *p)) for i, p in enumerate(poses)]
    for s in sims:
        assert np.allclose(s.truth.T_scanner_from_fiducial, T_sf, atol=1e-9)
    reg = register([s.slice for s in sims], neuro_geometry)
    assert len(reg.slices) == 3 and sum(s.n_tubes for s in reg.slices) == 27
    for s, p in zip(reg.slices, poses):
        assert s.depth_mm == pytest.approx(p[0], abs=0.1)
    pts = np.array([[0, 0, 0], [0, 0, 50], [12.5, 0, 25]], float)
    assert np.abs(apply(reg.T_scanner_from_fiducial, pts) - apply(T_sf, pts)).max() < 0.15


def test_slices_of_different_poses_do_not_lock(neuro_geometry):
    a = simulate_slice(neuro_geometry, 15, 0, 0, 0, rng=0)
    b = simulate_slice(neuro_geometry, 30, 0, 0, 0, rng=1)  # same image placement, different fiducial pose
    with pytest.raises(NoLock):
        register([a.slice, b.slice], neuro_geometry)


def test_a_series_decides_what_one_slice_cannot():
    """A slim needle guide (10 mm body, 0.8 mm channels; the optimiser's design for 0.3 mm pixels) seen normal to its
    axis: one slice alone fits two mirror tilts equally well and is refused; three parallel slices 1.5 mm apart
    refine every slice's candidates on all of them, single one out, and lock on the truth."""
    from chic_design.families import geometry_of
    from chic_design.optimize.confirm import simulate_parallel
    from chic_design.spec import load_spec

    geom = geometry_of(load_spec(ROOT / "tests" / "data" / "needle-guide-slim.yaml"))
    rng = np.random.default_rng(0)
    centre = np.array([0.0, 0.0, geom.body.length / 2, 1.0])
    locked = 0
    for draw in range(3):
        sims = simulate_parallel(geom, 17.5, 0.0, 37.0 * draw, 23.0 * draw, 3, 1.5, 0.3, 1.5, 20.0, rng)
        T_true = sims[0].truth.T_scanner_from_fiducial
        with pytest.raises(NoLock):
            register([sims[1].slice], geom)
        try:
            reg = register([s.slice for s in sims], geom)
        except NoLock:
            continue
        locked += 1
        assert np.linalg.norm((reg.T_scanner_from_fiducial - T_true) @ centre) < 0.3
    assert locked >= 2
