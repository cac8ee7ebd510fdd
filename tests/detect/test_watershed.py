"""The watershed the blob splitter uses is scipy.ndimage.watershed_ift's, pixel for pixel."""

import numpy as np
import pytest

from chic_register.detect.watershed import watershed_ift

ndi = pytest.importorskip("scipy.ndimage")


@pytest.mark.parametrize("seed", range(6))
def test_the_watershed_is_scipys_on_random_images_with_ties_and_background_seeds(seed):
    rng = np.random.default_rng(seed)
    for _ in range(150):
        H, W = (int(v) for v in rng.integers(2, 30, 2))
        top = int(rng.choice([2, 5, 50, 1000, 65535]))  # few levels (ties everywhere) to the full uint16 range
        depth = rng.integers(0, top + 1, (H, W)).astype(np.uint16)
        markers = np.zeros((H, W), np.int32)
        k = int(rng.integers(1, min(6, H * W) + 1))
        where = rng.choice(H * W, k, replace=False)
        markers.flat[where] = rng.choice([-1, 1, 2, 3, 4], k)
        np.testing.assert_array_equal(watershed_ift(depth, markers), ndi.watershed_ift(depth, markers))


def test_the_watershed_is_scipys_on_two_blurred_blobs_run_together():
    yy, xx = np.mgrid[0:24, 0:40].astype(float)
    smooth = np.exp(-((yy - 12) ** 2 + (xx - 13) ** 2) / 18) + 0.8 * np.exp(-((yy - 11) ** 2 + (xx - 26) ** 2) / 18)
    blob = smooth > 0.2
    markers = np.zeros(blob.shape, np.int32)
    markers[12, 13], markers[11, 26] = 1, 2
    markers[~blob] = -1
    depth = np.clip((smooth.max() - smooth) / (smooth.max() - 0.2) * 1000, 0, 65535).astype(np.uint16)
    ours = watershed_ift(depth, markers)
    np.testing.assert_array_equal(ours, ndi.watershed_ift(depth, markers))
    assert ours[12, 13] == 1 and ours[11, 26] == 2 and (ours == 1).sum() > 1 and (ours == 2).sum() > 1


def _component_with_seeds(rng):
    """``(depth, markers, mask)``: a random component (``mask``) with three object seeds, the rest background seeds,
    as the blob splitter floods one."""
    H, W = (int(v) for v in rng.integers(3, 25, 2))
    depth = rng.integers(0, int(rng.choice([3, 200, 2000])), (H, W)).astype(np.uint16)
    mask = rng.random((H, W)) < 0.7
    markers = np.where(mask, 0, -1).astype(np.int32)
    markers.flat[rng.choice(H * W, 3, replace=False)] = [1, 2, 3]
    return depth, markers, mask


def test_a_region_outgrowing_its_limit_stops_the_flood_exactly_when_the_full_flood_would_show_it():
    rng = np.random.default_rng(7)
    for _ in range(300):
        depth, markers, mask = _component_with_seeds(rng)
        H, W = depth.shape
        full = watershed_ift(depth, markers)
        largest = max(int(((full == g) & mask).sum()) for g in (1, 2, 3))
        limit = int(rng.integers(1, H * W))
        stopped = watershed_ift(depth, markers, mask, limit)
        assert (stopped is None) == (largest > limit)
        if stopped is not None:
            np.testing.assert_array_equal(stopped, full)


def test_a_remembered_flood_answers_as_a_fresh_one_for_any_region_limit():
    from chic_register.detect.watershed import forget_floods

    rng = np.random.default_rng(11)
    for _ in range(200):
        depth, markers, mask = _component_with_seeds(rng)
        limits = [int(v) for v in rng.integers(1, depth.size, 3)]
        forget_floods()
        fresh = []
        for limit in limits:
            forget_floods()
            fresh.append(watershed_ift(depth, markers, mask, limit))
        forget_floods()
        for limit, want in zip(limits, fresh):  # each asked in turn of the memory the earlier ones left
            got = watershed_ift(depth, markers, mask, limit)
            assert (got is None) == (want is None)
            if want is not None:
                np.testing.assert_array_equal(got, want)
                got[:] = 0  # a caller's change to its answer does not reach the memory
        full = watershed_ift(depth, markers)
        np.testing.assert_array_equal(full, ndi.watershed_ift(depth, markers))
