"""The tube model: plane crossings against the geometry objects, their Jacobian, the extent test's scalar path, and
the memos (prepared geometry, crossings, tubes' repr) that must give the same numbers as computing again.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.fit.section import tube_frames
from chic_register.model.geometry import content_sha256
from chic_register.model.pose import apply, invert, rigid, rot_y, rot_z, slice_frame
from chic_register.model.tube_model import (
    TubeModel,
    crossing_jacobian,
    crossings_memo,
    exp_se3,
    inside_mask,
    plane_crossings,
    poses_distinct,
    prepare_geometry,
)
from tests.helpers import near_end_slice


@pytest.mark.parametrize("pose", [(25, 0, 0, 0), (12, 35, 60, -20), (38, 55, 200, 75)])
def test_plane_crossings_match_the_geometry_objects(neuro_geometry, pose):
    T = slice_frame(*pose)
    model = TubeModel.from_geometry(neuro_geometry)
    xy, tan, z, inside = plane_crossings(model, T)
    ref = neuro_geometry.intersect_plane(T[:3, 3], T[:3, 2])
    for k, tid in enumerate(model.ids):
        pts = ref[tid]
        if len(pts) == 0:
            assert not inside[k]
            continue
        p_img = apply(invert(T), pts)
        j = int(np.argmin(np.linalg.norm(p_img[:, :2] - xy[k], axis=1)))
        assert np.allclose(p_img[j, :2], xy[k], atol=1e-7)
        assert abs(p_img[j, 2]) < 1e-9
        assert z[k] == pytest.approx(pts[j, 2], abs=1e-7)
        assert np.linalg.norm(tan[k]) == pytest.approx(1.0)


def test_crossing_jacobian_matches_finite_differences(neuro_geometry):
    model = TubeModel.from_geometry(neuro_geometry)
    T = slice_frame(20, 25, 30, 10)
    xy, tan, _, _ = plane_crossings(model, T)
    J = crossing_jacobian(xy, tan)
    h = 1e-6
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        xp, *_ = plane_crossings(model, T @ exp_se3(xi))
        xm, *_ = plane_crossings(model, T @ exp_se3(-xi))
        assert np.allclose((xp - xm) / (2 * h), J[:, :, i], atol=1e-5)


def test_prepared_geometry_follows_the_content(neuro_geometry, needle_geometry):
    import dataclasses

    model, sha = prepare_geometry(neuro_geometry)
    assert sha == content_sha256(neuro_geometry.content())
    assert model.ids == neuro_geometry.ids and prepare_geometry(neuro_geometry)[0] is model  # memoised
    # an equal copy shares the memo; any change of content (a tube, the source) gets its own model and hash
    copy = dataclasses.replace(neuro_geometry, source=dict(neuro_geometry.source))
    assert prepare_geometry(copy)[0] is model
    moved = dataclasses.replace(neuro_geometry, tubes=(dataclasses.replace(neuro_geometry.tubes[0], diameter=2.0),
                                                       *neuro_geometry.tubes[1:]))
    m2, sha2 = prepare_geometry(moved)
    assert sha2 == content_sha256(moved.content()) != sha and m2.diameter_mm[0] == 2.0
    other = dataclasses.replace(neuro_geometry, source={"spec": "elsewhere.yaml"})
    assert prepare_geometry(other)[1] == content_sha256(other.content()) != sha
    assert prepare_geometry(needle_geometry)[0].ids == needle_geometry.ids
    d0 = neuro_geometry.tubes[0]
    signed = dataclasses.replace(neuro_geometry, tubes=(
        dataclasses.replace(d0, p0=(d0.p0[0], -0.0, d0.p0[2])), *neuro_geometry.tubes[1:]))
    assert d0.p0[1] == 0.0 and prepare_geometry(signed)[1] == content_sha256(signed.content())


POSES = [(25, 0, 0, 0), (12, 35, 60, -20), (38, 55, 200, 75), (2, 70, 10, 5), (49, 20, 300, 40)]


def _inside_arrays(model, T, margin_mm):
    """plane_crossings' extent test as array formulas (its earlier implementation)."""
    _, tan_I, zF, _ = plane_crossings(model, T, margin_mm=5.0)
    ok = np.array(crossings_memo(model, np.asarray(T, float))[3])
    if margin_mm > 0:
        return ok & (zF >= model.z_lo - margin_mm - 1e-6) & (zF <= model.z_hi + margin_mm + 1e-6)
    cos_a = np.maximum(np.abs(tan_I[:, 2]), 1e-6)
    tan_z = np.array(crossings_memo(model, np.asarray(T, float))[4])
    clear = 0.5 * model.diameter_mm * np.sqrt(np.maximum(1 - cos_a * cos_a, 0.0)) / cos_a * np.abs(tan_z)
    return ok & (zF >= model.z_lo + clear - 1e-6) & (zF <= model.z_hi - clear + 1e-6)


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("margin_mm", [0.0, 1e-9, 5.0])
def test_scalar_extent_test_equals_the_array_formula(neuro_geometry, pose, margin_mm):
    model = TubeModel.from_geometry(neuro_geometry)
    T = slice_frame(*pose)
    hit = crossings_memo(model, T)
    got = inside_mask(model, hit, margin_mm)
    assert got.dtype == bool
    assert np.array_equal(got, _inside_arrays(model, T, margin_mm))


def test_plane_crossings_memo_hands_out_fresh_arrays(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    _, T = near_end_slice(neuro_geometry)
    fresh_model = TubeModel.from_geometry(neuro_geometry)  # its own (empty) memo
    for margin in (0.0, 1e-9, 5.0):
        first = plane_crossings(model, T, margin_mm=margin)
        for a in first:
            a[...] = 0  # a caller scribbling on its result
        again = plane_crossings(model, T, margin_mm=margin)
        want = plane_crossings(fresh_model, T.copy(), margin_mm=margin)
        assert all(np.array_equal(a, w) for a, w in zip(again, want))
    frames = tube_frames(model, T, *plane_crossings(model, T, margin_mm=1e-9)[:2])
    assert not any(f.flags.writeable for f in frames)  # shared by later calls: read-only


def test_crossing_jacobian_is_the_crossings_derivative(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    _, T = near_end_slice(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    J = crossing_jacobian(q[found], tan[found])
    h = 1e-6
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        up = plane_crossings(model, T @ exp_se3(xi), margin_mm=1e-9)[0][found]
        down = plane_crossings(model, T @ exp_se3(-xi), margin_mm=1e-9)[0][found]
        assert np.allclose((up - down) / (2 * h), J[:, :, i], atol=1e-4)


def test_geometry_key_memo_of_the_tubes_repr_is_the_repr(neuro_geometry):
    """The geometry key's memo of ``repr(tubes)`` serves a tuple of immutable tubes its own repr, another tuple (a
    changed tube) its own, and never memoises tubes holding a value a caller could change in place."""
    import dataclasses

    from chic_register.model.tube_model import (
        TUBES_REPR,
        GeometryKey,
        immutable_tubes,
        tubes_repr,
    )

    tubes = neuro_geometry.tubes
    assert immutable_tubes(tubes)
    assert GeometryKey(neuro_geometry).key[3] == repr(tubes) and tubes_repr(tubes) == repr(tubes)
    moved = tuple(dataclasses.replace(t, diameter=t.diameter + 0.5) if k == 4 else t for k, t in enumerate(tubes))
    other = dataclasses.replace(neuro_geometry, tubes=moved)
    assert GeometryKey(other).key[3] == repr(moved) != repr(tubes)
    assert GeometryKey(other) != GeometryKey(neuro_geometry)
    assert prepare_geometry(other)[1] != prepare_geometry(neuro_geometry)[1]
    held = tuple(dataclasses.replace(t, diameter=np.float64(t.diameter)) if k == 4 else t for k, t in enumerate(tubes))
    assert not immutable_tubes(held) and not immutable_tubes(list(tubes))
    tubes_repr(held)
    assert id(held) not in TUBES_REPR


@pytest.mark.parametrize("move, mm, distinct", [
    (rigid(np.eye(3), (0.0, 0.0, 0.0)), 1.0, False),  # the same pose
    (rigid(rot_z(1.5), (0.0, 0.0, 0.0)), 1.0, True),  # turned more than 1 deg
    (rigid(rot_z(0.8), (0.0, 0.0, 0.0)), 1.0, False),  # about the axis: the 12.5 mm circle moves 0.17 mm
    (rigid(rot_y(0.8), (0.0, 0.0, 0.0)), 1.0, False),  # about y through the bottom face: the top tube end moves 0.72 mm
    (rigid(rot_y(0.8), (0.0, 0.0, 0.0)), 0.5, True),  # ... more than 0.5 mm
    (rigid(np.eye(3), (0.9, 0.0, 0.0)), 1.0, False),  # shifted 0.9 mm
    (rigid(np.eye(3), (0.0, 0.0, 1.1)), 1.0, True),  # shifted 1.1 mm along the axis
])
@pytest.mark.parametrize("t_scanner_mm", [(4.0, -7.0, 60.0), (11.0, -14.8, -136.8)])
def test_poses_are_distinct_beyond_a_millimetre_at_a_tube_end_or_a_degree(neuro_geometry, move, mm, distinct,
                                                                           t_scanner_mm):
    """neuro's probe points: tube ends on the 12.5 mm circle at z = 0 and 50, a point on it at mid-length, the axis
    ends; the second pose is the first (an arbitrary one, near the isocentre or 137 mm from it as a real scan's
    frame) followed by ``move`` in F; both given as ``T_F_from_scanner``, as the solver holds them."""
    model, _ = prepare_geometry(neuro_geometry)
    T1 = rigid(rot_z(30.0) @ rot_y(20.0), t_scanner_mm)
    X1, X2 = invert(T1), invert(T1 @ move)
    assert poses_distinct(X1, X2, model, mm=mm) is distinct
    assert poses_distinct(X2, X1, model, mm=mm) is distinct
