"""Frame symmetries (chic_register.model.symmetry): an exact self-symmetry needs a prior, a near-twin does not."""


from __future__ import annotations

import numpy as np

from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.pipeline.register import register


def test_a_near_twin_a_pixel_away_is_for_the_image_to_decide(needle_geometry):
    """The needle guide's half turn leaves its tubes 0.63 mm apart: a near-twin, not a symmetry. At 0.8 mm pixels the
    solver must not refuse it up front as a self-symmetric frame (it refused every such needle-guide series);
    z001's exact symmetry still is refused up front."""
    from chic_register.model.symmetry import EXACT_SHARE, frame_symmetries, prior_needed

    d = min(t.diameter for t in needle_geometry.tubes)
    assert 0.5 < frame_symmetries(needle_geometry, 10.0)[1] < 0.8  # the near-twin's mismatch (mm)
    assert prior_needed(needle_geometry, EXACT_SHARE * d) is None
    sl = simulate_slice(needle_geometry, 20.0, 15.0, 40.0, 10.0, pixel_spacing_mm=(0.8, 0.8), shape=(64, 64), noise="rician", snr=30,
                        rng=2).slice
    try:
        register([sl], needle_geometry)
    except NoLock as exc:
        assert "maps onto itself" not in exc.reason


def test_the_solvers_coarse_symmetry_test_bounds_the_full_one_from_below(zframe_geometry, neuro_geometry, needle_geometry):
    """prior_needed first compares 9 of the 65 points per tube (a subset of the same pairs): each coarse mismatch
    is a lower bound, so a frame it clears has no symmetry, and the frames it does not clear get the full test."""
    from chic_register.model.symmetry import (
        EXACT_SHARE,
        candidate_rotations,
        mismatches,
        prior_needed,
    )

    for g in (zframe_geometry, neuro_geometry, needle_geometry):
        Rs = np.stack([R for _, R in candidate_rotations(g.body.length)])
        full, coarse = mismatches(g, Rs), mismatches(g, Rs, 9)
        assert all(c <= f + 1e-12 for (c, _), (f, _) in zip(coarse, full))
        assert min(f for f, _ in full) > 0.5 or g is zframe_geometry  # the CHIC designs are far from any symmetry
    assert prior_needed(zframe_geometry, EXACT_SHARE * 1.0) is not None
    assert prior_needed(neuro_geometry, 0.1) is None and prior_needed(needle_geometry, 0.1) is None
    assert prior_needed(needle_geometry, 0.7) is not None  # its half turn leaves the tubes 0.63 mm apart


def test_prior_needed_memo_gives_what_the_test_itself_gives(zframe_geometry, neuro_geometry, needle_geometry):
    """prior_needed is memoised per geometry and tolerance: every answer equals the unmemoised test's, on repeat
    calls too, and a different tolerance is not served another's answer."""
    from chic_register.model.symmetry import prior_needed, prior_needed_unmemoised

    for g in (zframe_geometry, neuro_geometry, needle_geometry):
        for tol in (0.05, 0.1, 0.7):
            want = prior_needed_unmemoised(g, tol)
            assert prior_needed(g, tol) == want and prior_needed(g, tol) == want
    assert prior_needed(needle_geometry, 0.1) is None and prior_needed(needle_geometry, 0.7) is not None
