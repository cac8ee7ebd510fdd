"""Frame symmetries (chic_register.model.symmetry): an exact self-symmetry needs a prior, a near-twin does not."""

from __future__ import annotations

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
