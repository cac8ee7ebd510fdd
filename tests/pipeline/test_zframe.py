"""Z-frame slices (z001 of 3D Slicer's ZFrameRegistration: seven line tubes) registered with an orientation prior,
in tissue with intensity falloff; refused without a prior, without the diagonals or with the wrong geometry.

Round trips: geometry -> simulated slice (Rician SNR 20) -> register -> compared with the known pose by the target
error at the frame's centre.
"""

import dataclasses

import numpy as np
import pytest
from scipy import ndimage as ndi

from chic_register.detect.blobs import detect_blobs
from chic_register.errors import NoLock
from chic_register.imaging.simulate import add_rician_noise, simulate_slice
from chic_register.model.pose import rigid, rot_y, rot_z
from chic_register.pipeline.register import register
from tests.helpers import ZF_CENTRE, rician_slice, right_or_refused, tre_mm

# chic_design.feasibility.tilt_search.tilt_limits at depth 30 mm (0.5 mm pixels, 2 mm slices): 30.70
ZF_LIMIT_DEG = 30.6


ZF_CASES = [  # (depth, tilt, azimuth, twist), width factor, distractors, missing tubes
    ((30, 0, 0, 0), 1.0, 0, ()),
    ((22, 12, 70, 25), 2.0, 0, ()),
    ((36, 18, 160, -40), 1.0, 5, ()),
    ((27, 10, 250, 100), 2.0, 4, ("A2",)),
    ((33, 8, 300, 5), 1.0, 0, ("Z1",)),
    ((30, ZF_LIMIT_DEG - 0.5, 45, 15), 1.0, 0, ()),
    ((30, ZF_LIMIT_DEG - 0.5, 200, 15), 2.0, 0, ()),
]


@pytest.mark.parametrize("pose, width, distractors, missing", ZF_CASES)
def test_zframe_slice_registers(z001, pose, width, distractors, missing):
    sl, T_true = rician_slice(z001, pose, width=width, seed=int(pose[2]), distractors=distractors, missing=missing)
    prior = rigid(T_true[:3, :3] @ rot_z(25) @ rot_y(20), (0, 0, 0))  # an orientation known to ~30 degrees
    reg = register([sl], z001, prior=prior)
    assert tre_mm(reg.T_scanner_from_fiducial, T_true, ZF_CENTRE) < 0.3
    assert reg.slices[0].n_tubes == 7 - len(missing)


def test_zframe_is_self_symmetric_so_no_prior_is_refused(z001):
    """A half turn about y through the centre maps the z001 frame onto itself: without a prior, no guess."""
    sl, _ = rician_slice(z001, (24, 10, 30, 20), seed=1)
    with pytest.raises(NoLock, match="ambiguous fit.*--prior"):
        register([sl], z001)


@pytest.mark.parametrize("pose", [(30, 0, 0, 0), (22, 12, 70, 25)])
def test_zframe_in_tissue_with_intensity_falloff_registers(z001, pose):
    """Wide blobs, a bright body region swallowing two rods and a 2:1 coil-sensitivity ramp across the image.

    As it is, the rods in the tissue merge with it and are lost: the solver
    retries on the flattened image (top-hat at three blob widths) and locks.
    """
    rng = np.random.default_rng(11)
    sim = simulate_slice(z001, *pose, noise="none", rng=rng, slice_thickness_mm=3.0)
    img = ndi.gaussian_filter(sim.slice.pixels, 2.5)  # blobs about twice as wide as the rods
    img /= img.max()
    rows, cols = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    tissue = 0.6 * ndi.gaussian_filter(((cols - 128) / 120.0) ** 2 + ((rows - 250) / 90.0) ** 2 < 1.0, 4.0)
    img = add_rician_noise(np.maximum(img, tissue) * (1.0 - 0.5 * cols / img.shape[1]), 20.0, rng)
    sl = dataclasses.replace(sim.slice, pixels=img)
    T_true = sim.truth.T_scanner_from_fiducial
    assert len(detect_blobs(img, sl.pixel_spacing_mm, 3.0)) < 7  # the plain detector loses rods here
    prior = rigid(T_true[:3, :3], (0, 0, 0))
    reg = register([sl], z001, prior=prior, verify=False)
    assert tre_mm(reg.T_scanner_from_fiducial, T_true, ZF_CENTRE) < 0.3 and reg.slices[0].n_tubes >= 6
    right_or_refused(sl, z001, T_true, ZF_CENTRE, prior=prior)


def test_no_lock_without_the_depth_tubes_or_with_the_wrong_geometry(z001, neuro_geometry):
    """The generic stage never invents a pose: rods without their diagonals (plus stray blobs), a CHIC slice."""
    for seed, pose in enumerate([(30, 5, 40, 0), (25, 15, 200, 30)]):
        sl, T_true = rician_slice(z001, pose, seed=seed, distractors=6, missing=("Z0", "Z1", "Z2"))
        with pytest.raises(NoLock):
            register([sl], z001, prior=T_true)
        chic, _ = rician_slice(neuro_geometry, (25, pose[1], pose[2], 0), seed=seed, distractors=3)
        with pytest.raises(NoLock):
            register([chic], z001, prior=rigid(np.eye(3), (0, 0, 0)), prior_max_deg=180)
