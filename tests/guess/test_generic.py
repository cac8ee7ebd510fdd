"""The generic first guess (chic_register.guess.generic) of fiducials with parallel tubes: rotations from an affine
map, guesses from exact crossings, sampled triples.

The Z-frame is z001 of 3D Slicer's ZFrameRegistration (tests.helpers.zframe).
"""

import math

import numpy as np
import pytest

from chic_register.guess.generic import family_hypotheses, parallel_family, rotations_from_affine
from chic_register.model.pose import slice_frame
from chic_register.model.tube_model import plane_crossings, prepare_geometry


def test_rotations_from_an_affine_map_recover_the_cut(z001):
    """Hand-built: the image-to-section map of a known cut gives back its rotation (one of two signs)."""
    model, _ = prepare_geometry(z001)
    fam = parallel_family(model)
    assert list(np.array(model.ids)[fam.idx]) == ["A0", "A1", "A2", "A3"] and np.allclose(fam.u, [0, 0, 1])
    for pose in [(30, 0, 0, 0), (20, 25, 40, 10), (40, 60, 200, -70)]:
        R = slice_frame(*pose)[:3, :3]
        A = fam.E.T @ R[:, :2]  # section coordinates of an image point p are A p + const
        got = rotations_from_affine(A, fam, math.cos(math.radians(80)))
        assert min(np.abs(Rg - R).max() for Rg, _ in got) < 1e-9
        assert len(got) == (1 if pose[1] == 0 else 2)


@pytest.mark.parametrize("geom_name", ["zframe", "neuro", "needle"])
def test_generic_guesses_contain_the_pose_from_exact_crossings(geom_name, z001, neuro_geometry, needle_geometry):
    """No image: the true crossings plus two stray points; a guess lands near the truth for every pose."""
    geom = {"zframe": z001, "neuro": neuro_geometry, "needle": needle_geometry}[geom_name]
    model, _ = prepare_geometry(geom)
    rng = np.random.default_rng(3)
    L = geom.body.length
    for _ in range(6):
        T = slice_frame(rng.uniform(0.35, 0.65) * L, rng.uniform(0, 20), rng.uniform(0, 360), rng.uniform(-180, 180))
        q, _, _, inside = plane_crossings(model, T)
        xy = np.concatenate([q[inside], rng.uniform(-40, 40, (2, 2))])
        hyps = family_hypotheses(model, xy, gate_mm=3.0)
        err = [max(np.abs(H[:3, :3] - T[:3, :3]).max() * 40, np.abs(H[:3, 3] - T[:3, 3]).max()) for H in hyps]
        assert hyps and min(err) < 3.0, (T, err)


def test_first_guess_on_hundreds_of_specks_samples_its_triples(z001):
    """300 candidate blobs (an image strewn with bright specks): C(300, 3) = 4.5 million triples are sampled to the
    pair budget, not enumerated (that allocated gigabytes), and the nearest-blob search agrees with brute force."""
    from chic_register.guess.generic import (
        affine_candidates,
        nearest_blob_mm,
        parallel_family,
    )
    from chic_register.model.tube_model import prepare_geometry

    model, _ = prepare_geometry(z001)
    fam = parallel_family(model)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-40, 40, (300, 2))
    blob_t, ti = affine_candidates(fam, xy, 3.0, math.cos(math.radians(75)), 4000, rng)
    assert blob_t.shape[0] == ti.shape[0] and blob_t.shape[0] <= 4000 * 2
    assert np.all(blob_t[:, 0] < blob_t[:, 1]) and np.all(blob_t[:, 1] < blob_t[:, 2])
    pred = rng.uniform(-40, 40, (50, 4, 2))
    brute = np.linalg.norm(pred[:, :, None, :] - xy[None, None], axis=-1).min(axis=2)
    assert np.allclose(nearest_blob_mm(pred, xy), brute)
