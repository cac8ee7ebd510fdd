"""The efficiency study (chic_register.studies.efficiency): the ratio's bootstrap interval and adaptive draws."""

from __future__ import annotations

import numpy as np

from chic_register.studies.efficiency import pose_efficiency, ratio_interval


def test_ratio_interval_covers_the_truth_and_narrows_with_draws():
    rng = np.random.default_rng(2)
    crlb = np.array([1.0, 2.0, 0.5, 3.0])
    covered = 0
    for _ in range(40):
        e = rng.normal(size=(100, 4)) * crlb
        ci = ratio_interval(e, crlb, seed=1)
        covered += int(np.sum((ci[:, 0] <= 1.0) & (ci[:, 1] >= 1.0)))
    assert covered >= 0.88 * 160
    wide = np.diff(ratio_interval(rng.normal(size=(50, 4)) * crlb, crlb), axis=1)
    narrow = np.diff(ratio_interval(rng.normal(size=(800, 4)) * crlb, crlb), axis=1)
    assert np.all(narrow < 0.5 * wide)
    assert np.isnan(ratio_interval(np.zeros((1, 4)), crlb)).all()


def test_adaptive_draws_run_whole_batches_and_keep_every_draw(neuro_geometry):
    r = pose_efficiency(neuro_geometry, 25.0, 20.0, 30.0, 0.0, snr=20.0, draws=4, draws_max=12, seed=5,
                        crlb_quality="fast")
    assert r.draws in (4, 8, 12)
    assert r.errors.shape == (r.draws - r.no_lock, 4)
    assert np.allclose(r.rms, np.sqrt(np.mean(r.errors**2, axis=0)))
    assert r.ratio_ci.shape == (4, 2) and np.all(r.ratio_ci[:, 0] <= r.ratio) and np.all(r.ratio <= r.ratio_ci[:, 1])
    if r.draws < 12:  # stopped early: no interval contains the target
        assert not np.any((r.ratio_ci[:, 0] <= 1.15) & (r.ratio_ci[:, 1] >= 1.15))
