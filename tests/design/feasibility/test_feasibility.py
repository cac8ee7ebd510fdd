"""Feasibility checks against hand-worked cases, and infeasible specs rejected with their violations."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from chic_design.cli.main import main
from chic_design.families import FAMILIES
from chic_design.feasibility.contacts import touching_channels
from chic_design.feasibility.depth_precision import depth_sensitivity
from chic_design.feasibility.engine import check_geometry
from chic_design.feasibility.printability import channel_clearances, channel_overhangs
from chic_design.feasibility.tilt_search import tilt_limits
from chic_design.feasibility.unambiguity import pattern_symmetries
from chic_design.spec import load_spec, parse_spec
from chic_register.model.body import Body
from chic_register.model.centreline_crossings import plane_crossings
from chic_register.model.envelope import OUTSIDE, clipped_disc_distance, plane_normals, section_gap
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import HelixTube, LineTube

CHIC = FAMILIES["chic"]

NEURO = "designs/neuro.yaml"
NEEDLE = "designs/needle-guide.yaml"


def _spec_dict(path=NEURO, **changes):
    data = yaml.safe_load(open(path, encoding="utf-8"))
    for dotted, value in changes.items():
        node = data
        *parents, key = dotted.split("__")
        for p in parents:
            node = node.setdefault(p, {})
        node[key] = value
    return data


def _spec(path=NEURO, **changes):
    return parse_spec(_spec_dict(path, **changes))


@pytest.fixture(scope="module")
def neuro_ideal():
    return CHIC.check(load_spec(NEURO), pixel_size_mm=0.0, slice_thickness_mm=0.0)


# ------------------------------------------------------------------ plane crossings


def test_plane_through_straight_tube_matches_hand_and_intersect_plane():
    tube = LineTube("D0", "diametric", (12.5, 0, 0), (12.5, 0, 50), 3.0)
    tilt, az = 30.0, 0.0
    n = plane_normals(tilt, az)[None, :]
    o = np.array([[0.0, 0.0, 25.0]])
    t, p, tg, cnt = plane_crossings(tube, o, n)
    # plane z = 25 - tan(30) x  ->  z = 25 - 12.5 tan 30 at x = 12.5
    assert cnt[0] == 1
    assert p[0] == pytest.approx([12.5, 0.0, 25 - 12.5 * math.tan(math.radians(30))], abs=1e-9)
    assert p[0] == pytest.approx(tube.intersect_plane(o[0], n[0])[0], abs=1e-9)
    assert tg[0] == pytest.approx([0, 0, 1])
    # a plane steep enough to pass the tube's end misses it: tan(tilt) > 25 / 12.5
    n2 = plane_normals(64.0, 0.0)[None, :]
    t2, p2, _, cnt2 = plane_crossings(tube, o, n2)
    assert cnt2[0] == 0 and np.isnan(t2[0]) and np.isnan(p2[0]).all()
    assert tube.intersect_plane(o[0], n2[0]).shape == (0, 3)


def test_helix_crossings_match_intersect_plane():
    helix = HelixTube("H0", "helix", 12.5, 10.0, 1.4, 0.0, 50.0, 3.0)
    rng = np.random.default_rng(3)
    P = 200
    tilt = rng.uniform(0, 60, P)
    az = rng.uniform(0, 360, P)
    z = rng.uniform(5, 45, P)
    n = plane_normals(tilt, az)
    o = np.zeros((P, 3))
    o[:, 2] = z
    _, pts, tg, cnt = plane_crossings(helix, o, n)
    for k in range(P):
        ref = helix.intersect_plane(o[k], n[k])
        assert cnt[k] == len(ref)
        if len(ref):
            assert pts[k] == pytest.approx(ref[0], abs=1e-7)
            assert abs(n[k] @ (pts[k] - o[k])) < 1e-6
            assert tg[k] == pytest.approx(helix.tangents([(pts[k, 2] - 0.0) / 50.0])[0], abs=1e-6)


# ------------------------------------------------------------------ tilt limits


def test_visibility_limit_is_atan_half_length_over_radius(neuro_ideal):
    """Paper: 63.5 deg at mid-depth of the prototype, i.e. atan(25 / 12.5)."""
    mid = neuro_ideal.mid_depth_limit
    assert mid.depth_mm == 25.0
    assert mid.visibility_tilt_deg == pytest.approx(math.degrees(math.atan(25 / 12.5)), abs=0.1)
    # away from the middle the visibility limit is atan(min(z, L - z) / r) as well
    for lim in neuro_ideal.tilt_limits:
        if 10 <= lim.depth_mm <= 40:
            expect = math.degrees(math.atan(min(lim.depth_mm, 50 - lim.depth_mm) / 12.5))
            assert lim.visibility_tilt_deg == pytest.approx(expect, abs=0.1)
    # the full limit can only be lower, and names what sets it
    assert mid.max_tilt_deg <= mid.visibility_tilt_deg + 1e-9
    assert mid.limited_by.startswith(("tubes_merge:", OUTSIDE))
    text = neuro_ideal.summary_text()
    assert "mid-depth z = 25 mm" in text and mid.limited_by in text and "63.4 deg" in text


def test_straight_tubes_only_are_limited_by_visibility():
    geom = FiducialGeometry("lines", Body(50, 30, 20), tuple(
        LineTube(f"D{i}", "diametric", (12.5 * math.cos(a), 12.5 * math.sin(a), 0),
                 (12.5 * math.cos(a), 12.5 * math.sin(a), 50), 3.0)
        for i, a in enumerate(np.radians([0, 90, 180, 270]))))
    lims = tilt_limits(geom, 0.0, 0.0, depths_mm=[10.0, 25.0])
    for lim in lims:
        assert lim.limited_by == OUTSIDE
        assert lim.max_tilt_deg == pytest.approx(math.degrees(math.atan(min(lim.depth_mm, 50 - lim.depth_mm) / 12.5)),
                                                 abs=0.1)


def _two_parallel_tubes(d=3.0):
    return FiducialGeometry("pair", Body(200, 40, 2), (
        LineTube("A", "other", (10, 0, 0), (10, 0, 200), d),
        LineTube("B", "other", (15, 0, 0), (15, 0, 200), d),
    ))


def test_two_tubes_merge_at_hand_worked_tilt():
    """Tubes at x = 10 and 15, d = 3, slice s = 4, no pixel gap.

    Tilting about y (azimuth 0): centres 5/cos(T) apart, each blob reaches
    (d/2)/cos(T) + (s/2) tan(T) toward the other, so they touch when
    5 - 3 = s sin(T): sin(T) = 0.5, T = 30 deg.
    """
    lim = tilt_limits(_two_parallel_tubes(), 0.0, 4.0, depths_mm=[100.0])[0]
    assert lim.max_tilt_deg == pytest.approx(30.0, abs=0.1)
    assert lim.limited_by == "tubes_merge:A/B"
    assert math.cos(math.radians(lim.azimuth_deg)) ** 2 == pytest.approx(1.0, abs=1e-3)


def test_pixel_gap_enters_merge_condition():
    """Same pair, s = 4, pixel 0.5: 2 - 4 sin T = 0.5 cos T."""
    expect = math.degrees(next(t for t in np.linspace(0, 1.2, 1_200_001)
                               if 2 - 4 * math.sin(t) - 0.5 * math.cos(t) <= 0))
    lim = tilt_limits(_two_parallel_tubes(), 0.5, 4.0, depths_mm=[100.0])[0]
    assert lim.max_tilt_deg == pytest.approx(expect, abs=0.1)
    # no smear: an oblique cut stretches gaps, the pair never merges; visibility sets the limit
    lim0 = tilt_limits(_two_parallel_tubes(), 0.5, 0.0, depths_mm=[100.0])[0]
    assert lim0.limited_by == OUTSIDE
    assert lim0.max_tilt_deg == pytest.approx(math.degrees(math.atan(100 / 15)), abs=0.1)


def test_overlapping_tubes_fail_at_tilt_zero():
    lim = tilt_limits(_two_parallel_tubes(d=5.2), 0.0, 0.0, depths_mm=[100.0])[0]
    assert not lim.usable_at_zero_tilt and lim.max_tilt_deg == 0.0
    assert lim.limited_by == "tubes_merge:A/B"


def test_ends_are_unusable_and_usable_depth_shrinks_with_tilt(neuro_ideal):
    first, last = neuro_ideal.tilt_limits[0], neuro_ideal.tilt_limits[-1]
    assert first.depth_mm == 0.0 and last.depth_mm == 50.0
    # helices start 10 deg from the diametric tubes: 25 sin 5 deg < 3 mm, they overlap
    assert not first.usable_at_zero_tilt and first.limited_by.startswith("tubes_merge:H")
    totals = [u.total_mm for u in neuro_ideal.usable_depth]
    assert [u.tilt_deg for u in neuro_ideal.usable_depth] == [0, 15, 30, 45]
    assert totals == sorted(totals, reverse=True) and totals[0] > 0
    for u in neuro_ideal.usable_depth:
        for a, b in u.ranges_mm:
            for lim in neuro_ideal.tilt_limits:
                if a <= lim.depth_mm <= b:
                    assert lim.usable_at_zero_tilt and lim.max_tilt_deg >= u.tilt_deg


def test_thicker_slice_lowers_the_limit():
    spec = load_spec(NEURO)
    thin = tilt_limits(CHIC.geometry(spec), 0.5, 0.0, depths_mm=[25.0])[0]
    thick = tilt_limits(CHIC.geometry(spec), 0.5, 3.0, depths_mm=[25.0])[0]
    assert thick.max_tilt_deg < thin.max_tilt_deg


# ------------------------------------------------------------------ clearances, overhang


def _solid_overlap_top_mm(helix, x_mm: float, r_mm: float) -> float:
    """Highest z where the helix channel and the vertical channel at (x, 0) share a point, by brute force.

    At height z the vertical channel is a disc of radius r; a point of the helix
    channel lies in it iff some helix centreline point q is within r of the disc:
    sqrt((q_z - z)^2 + max(0, rho - r)^2) <= r with rho = |q_xy - (x, 0)|.
    """
    q = helix.points(np.linspace(0.0, 0.2, 40001))  # z 0..10 mm at 0.25 um steps
    rho = np.maximum(np.hypot(q[:, 0] - x_mm, q[:, 1]) - r_mm, 0.0)
    zs = np.arange(0.0, 6.0, 0.002)
    hit = [np.min((q[:, 2] - z) ** 2 + rho**2) <= r_mm**2 for z in zs]
    return float(zs[np.flatnonzero(hit)[-1]])


def test_helix_diametric_intersection_z_range_matches_hand():
    """H0 at 10 + 1.4 z deg, D0 at 0 deg on r = 12.5: closest where 25 sin(5 deg) - 3 (hand); the
    z-range of the touch is the solids' overlap, checked against a 3-D brute force."""
    geom = CHIC.geometry(load_spec(NEURO))
    clear, viol, warn = channel_clearances(geom, 0.8)
    c = next(c for c in clear if (c.a, c.b) == ("H0", "D0"))
    assert c.status == "intersect"
    assert c.gap_mm == pytest.approx(25 * math.sin(math.radians(5)) - 3, abs=1e-3)
    z_end = _solid_overlap_top_mm(geom.tube("H0"), 12.5, 1.5)
    # the centrelines come within 3 mm only up to 2.68 mm; the solids overlap higher (2.9 mm)
    assert z_end > (2 * math.degrees(math.asin(3 / 25)) - 10) / 1.4 + 0.15
    assert len(c.intersect_z_mm) == 1
    assert c.intersect_z_mm[0][0] == 0.0 and c.intersect_z_mm[0][1] == pytest.approx(z_end, abs=0.06)
    # one answer: the report's touching channels are the same pairs and ranges
    assert ("D0", "H0", 0.0, c.intersect_z_mm[0][1]) in touching_channels(geom)
    assert any(w.code == "channels_intersect" and w.where == "H0/D0" for w in warn)
    assert not viol  # the prototype's walls are fine: 12.5 - 10 - 1.5 = 1.0 mm
    bore = next(c for c in clear if (c.a, c.b) == ("D0", "bore"))
    assert bore.gap_mm == pytest.approx(1.0, abs=1e-9)
    faces = [c for c in clear if c.b in ("bottom_face", "top_face")]
    assert faces and all(c.status == "open" for c in faces)


@pytest.mark.parametrize("inner, ok", [(20.4, True), (20.42, False)])
def test_wall_exactly_at_minimum_passes_thinner_fails(inner, ok):
    # channel circle 25 mm, d = 3: bore wall = 12.5 - inner/2 - 1.5 = 0.8 mm for inner 20.4
    spec = _spec(body__inner_diameter=inner, channels__circle_diameter=25.0)
    _, viol, _ = channel_clearances(CHIC.geometry(spec), spec.print.min_wall)
    assert (not viol) == ok
    if not ok:
        assert {v.code for v in viol} == {"wall_too_thin"}
        assert all("bore" in v.message for v in viol)


def test_channel_ending_inside_the_body_is_checked_against_its_face():
    body = Body(50, 30, 20)
    tubes = (LineTube("A", "other", (12.5, 0, 2.0), (12.5, 0, 50), 3.0),
             LineTube("B", "other", (-12.5, 0, 2.4), (-12.5, 0, 50), 3.0))
    clear, viol, _ = channel_clearances(FiducialGeometry("ends", body, tubes), 0.8)
    by = {(c.a, c.b): c for c in clear}
    assert by[("A", "bottom_face")].gap_mm == pytest.approx(0.5) and by[("A", "bottom_face")].status == "too_thin"
    assert by[("B", "bottom_face")].gap_mm == pytest.approx(0.9) and by[("B", "bottom_face")].status == "ok"
    assert by[("A", "top_face")].status == "open"
    assert [v.where for v in viol] == ["A bottom_face"]


def test_overhang_of_helix_is_its_lead_angle():
    geom = CHIC.geometry(load_spec(NEURO))
    expect = math.degrees(math.atan(12.5 * math.radians(1.4)))
    ov, viol = channel_overhangs(geom, 45.0)
    by = {o.tube_id: o.max_overhang_deg for o in ov}
    assert by["H0"] == pytest.approx(expect, abs=1e-6) and by["D0"] == pytest.approx(0.0, abs=1e-6)
    assert not viol
    _, viol = channel_overhangs(geom, 15.0)
    assert {v.where for v in viol} == {"H0", "H1", "H2"}
    assert all(v.code == "overhang_too_steep" for v in viol)


# ------------------------------------------------------------------ unambiguity, sensitivity


def test_depth_sensitivity_hand_values():
    ds = depth_sensitivity(CHIC.geometry(load_spec(NEURO)), 0.5)
    assert dict(ds.per_helix_mm_per_deg)["H0"] == pytest.approx(1 / 1.4)
    sigma_z = math.degrees(0.5 / math.sqrt(12) / 12.5) / 1.4
    assert dict(ds.per_helix_sigma_z_mm)["H1"] == pytest.approx(sigma_z)
    assert ds.combined_sigma_z_mm == pytest.approx(sigma_z / math.sqrt(3))


def test_symmetry_detector_on_hand_patterns():
    body = Body(10, 30, 20)

    def ring(angles):
        return FiducialGeometry("ring", body, tuple(
            LineTube(f"T{i}", "other", (12.5 * math.cos(math.radians(a)), 12.5 * math.sin(math.radians(a)), 0),
                     (12.5 * math.cos(math.radians(a)), 12.5 * math.sin(math.radians(a)), 10), 1.0)
            for i, a in enumerate(angles)))

    syms, _ = pattern_symmetries(ring([0, 120, 240]), [5.0], 0.1)
    assert syms and syms[0].mismatch_mm == pytest.approx(0, abs=1e-9)
    syms, _ = pattern_symmetries(ring([0, 90, 225]), [5.0], 0.1)  # isosceles: mirror about 45/225
    assert [s.kind for s in syms] == ["reflection"] and syms[0].angle_deg == pytest.approx(45.0)
    syms, m = pattern_symmetries(ring([0, 70, 160, 250]), [5.0], 0.1)  # scalene: no symmetry
    assert not syms and m > 1.0


def test_symmetric_orientation_tubes_are_rejected():
    """orientation [300, 330] with diametric at 270/360: mirror about the 135/315 deg line at mid-depth."""
    rep = CHIC.check(_spec(markers__orientation_deg=[300, 330]))
    assert not rep.feasible
    sym = [v for v in rep.violations if v.code == "symmetric_pattern"]
    assert sym
    hit = [s for s in rep.unambiguity.symmetries if s.depth_range_mm[0] <= 25 <= s.depth_range_mm[1]]
    assert hit and hit[0].kind == "reflection"
    assert hit[0].angle_deg == pytest.approx(135.0, abs=0.5)


def test_helix_leaving_its_quadrant_is_rejected():
    # pitch 3 deg/mm from 10 deg: reaches D1 (90 deg) at z = 80/3 mm
    rep = CHIC.check(_spec(helix__pitch_deg_per_mm=3.0))
    found = [v for v in rep.violations if v.code == "helix_leaves_quadrant"]
    assert found and not rep.feasible
    h0 = next(v for v in found if v.where.startswith("H0/D1"))
    assert f"z={80 / 3:.1f}" in h0.where


def test_prototype_is_feasible_and_unambiguous():
    rep = CHIC.check(load_spec(NEURO))
    assert rep.feasible, rep.violations
    assert rep.unambiguity.min_mismatch_mm > rep.unambiguity.tolerance_mm
    d = rep.to_dict()
    assert d["feasible"] is True and d["violations"] == []
    assert {"depth_mm", "max_tilt_deg", "limited_by"} <= set(d["tilt_limits"][0])
    for key in ("warnings", "usable_depth", "clearances", "overhangs", "unambiguity", "depth_sensitivity", "protocol"):
        assert key in d
    assert d["protocol"] == {"pixel_size_mm": 0.5, "slice_thickness_mm": 2.0}
    depths = [t["depth_mm"] for t in d["tilt_limits"]]
    assert depths[0] == 0 and depths[-1] == 50 and max(np.diff(depths)) <= 1.0
    assert "tilt_limits.png" in rep.markdown()


def test_needle_guide_with_asymmetric_orientation_tubes_is_feasible():
    """Orientation tubes at [295, 320] make the needle-guide mirror-symmetric at z ~ 23.3 mm; the shipped [294, 330] does not."""
    bad = CHIC.check(_spec(NEEDLE, markers__orientation_deg=[295, 320]))
    assert [v.code for v in bad.violations] == ["symmetric_pattern"]
    rep = CHIC.check(load_spec(NEEDLE))
    assert list(load_spec(NEEDLE).markers.orientation_deg) == [294, 330]
    assert rep.feasible, rep.violations


# ------------------------------------------------------------------ CLI


def _write(tmp_path, name, data):
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(data), encoding="utf-8")
    return str(p)


@pytest.mark.parametrize("changes, code", [
    ({"body__inner_diameter": 20.42, "channels__circle_diameter": 25.0}, "wall_too_thin"),
    ({"helix__pitch_deg_per_mm": 3.0}, "helix_leaves_quadrant"),
    ({"markers__orientation_deg": [300, 330]}, "symmetric_pattern"),
])
def test_cli_rejects_infeasible_specs(tmp_path, capsys, changes, code):
    path = _write(tmp_path, code, _spec_dict(**changes))
    assert main(["check", path, "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["feasible"] is False
    assert code in {v["code"] for v in out["violations"]}
    assert all(set(v) == {"code", "message", "where"} for v in out["violations"])


def test_cli_prototype_ideal_imaging_and_plot(tmp_path, capsys):
    png = tmp_path / "out" / "tilt_limits.png"
    assert main(["check", NEURO, "--slice-thickness", "0", "--pixel-size", "0", "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "tilt limit at mid-depth z = 25 mm" in text and "63.4 deg" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["check", NEURO, "--pixel-size", "-1"]) == 2


def test_batch_and_single_depth_evaluations_agree(neuro_ideal):
    """Regression: the limit at one depth must not depend on which other planes share the batch."""
    geom = CHIC.geometry(load_spec(NEURO))
    for z in (12.0, 25.0):
        single = tilt_limits(geom, 0.0, 0.0, depths_mm=[z])[0]
        batch = next(t for t in neuro_ideal.tilt_limits if t.depth_mm == z)
        assert single.max_tilt_deg == pytest.approx(batch.max_tilt_deg, abs=0.06)


def test_no_usable_depth_is_a_violation():
    rep = check_geometry(_two_parallel_tubes(d=5.2), CHIC, pixel_size_mm=0.0, slice_thickness_mm=0.0,
                           min_wall_mm=0.8, max_overhang_deg=45.0)
    assert "no_usable_depth" in {v.code for v in rep.violations} and not rep.feasible
    assert all(u.ranges_mm == () for u in rep.usable_depth)


# ------------------------------------------------------------------ exact blob gap vs brute force


def _brute_gap(ta, tb, o, n, length_mm, h=0.02, box=5.0):
    """Gap between two tubes' sections (zero slice thickness) on a fine in-plane grid of spacing h.

    A grid point is in a tube's blob if it is within d/2 of the densely sampled
    centreline and inside the body's z range. Returns (lower, upper) bounds on
    the true gap: the grid distance minus / plus one cell diagonal.
    """
    from scipy.spatial import cKDTree

    pa, pb = ta.intersect_plane(o, n)[0], tb.intersect_plane(o, n)[0]
    u = np.cross(n, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    g = np.arange(-box, box + h / 2, h)
    X, Y = np.meshgrid(g, g, indexing="ij")
    P = 0.5 * (pa + pb) + X.ravel()[:, None] * u + Y.ravel()[:, None] * v
    blobs = []
    for tube in (ta, tb):
        d, _ = cKDTree(tube.points(np.linspace(0, 1, int(tube.length_mm / 0.01) + 1))).query(P)
        blobs.append(P[(d <= tube.diameter / 2) & (P[:, 2] >= 0) & (P[:, 2] <= length_mm)])
    d = cKDTree(blobs[0]).query(blobs[1])[0].min()
    return d - h * math.sqrt(2), d + h * math.sqrt(2)


def test_section_gap_matches_brute_force_on_helix_and_line_at_steep_tilt():
    geom = CHIC.geometry(load_spec(NEURO))
    h0, d0 = geom.tube("H0"), geom.tube("D0")
    o = np.array([0.0, 0.0, 25.0])
    for tilt, az in ((55.0, 10.0), (60.0, 7.0), (61.0, 6.0)):
        n = plane_normals(tilt, az)
        gap = section_gap(h0, d0, o[None], n[None], 0.0, 50.0)[0][0]
        lo, hi = _brute_gap(h0, d0, o, n, 50.0)
        if lo > 0:  # clearly separate: the distance itself
            assert lo - 0.01 <= gap <= hi + 0.01, (tilt, gap, lo, hi)
        else:  # overlapping: only the sign is meaningful
            assert gap < 0


def test_exact_limit_brackets_brute_force_merge():
    """Helix/line pair at steep tilt: at the exact limit the brute-force gap is >= one pixel, 0.2 deg above it < one pixel."""
    geom = FiducialGeometry("pair", Body(50, 30, 20), (
        HelixTube("H0", "helix", 12.5, 10.0, 1.4, 0.0, 50.0, 3.0),
        LineTube("D0", "diametric", (12.5, 0, 0), (12.5, 0, 50), 3.0)))
    pixel = 0.3
    lim = tilt_limits(geom, pixel, 0.0, depths_mm=[25.0], exact=True)[0]
    assert lim.limited_by == "tubes_merge:H0/D0" and 45 < lim.max_tilt_deg < 63
    o = np.array([0.0, 0.0, 25.0])
    lo, _ = _brute_gap(geom.tubes[0], geom.tubes[1], o, plane_normals(lim.max_tilt_deg, lim.azimuth_deg), 50.0)
    _, hi = _brute_gap(geom.tubes[0], geom.tubes[1], o, plane_normals(lim.max_tilt_deg + 0.2, lim.azimuth_deg), 50.0)
    assert lo >= pixel - 0.03 and hi < pixel
    fast = tilt_limits(geom, pixel, 0.0, depths_mm=[25.0])[0]
    assert fast.max_tilt_deg <= lim.max_tilt_deg + 0.1  # the ellipse model is conservative here


def test_clipped_disc_distance_hand_cases():
    G = np.array([0.0, 1.0, 0.0])  # face line y = 0, half-plane y >= 0 kept
    c1, c2 = np.array([0.0, 1.0, 0.0]), np.array([3.0, 1.0, 0.0])
    one = np.array(1.0)
    # both discs inside-ish: arc points on the centre line lie in y >= 0 -> 3 - 2
    assert clipped_disc_distance(c1, one, c2, one, G, np.array(1.0), np.array(1.0)) == pytest.approx(1.0)
    # centres below the line at y = -0.6: caps with chords |x - cx| <= 0.8 on y = 0 -> 3 - 1.6
    c1b, c2b = c1 - [0, 1.6, 0], c2 - [0, 1.6, 0]
    assert clipped_disc_distance(c1b, one, c2b, one, G, np.array(-0.6), np.array(-0.6)) == pytest.approx(1.4)
    # overlapping discs whose lens lies below the line: chords 0.8 wide at centres 1.2 apart -> no overlap
    c2c = c1b + [1.9, 0, 0]
    assert clipped_disc_distance(c1b, one, c2c, one, G, np.array(-0.6), np.array(-0.6)) == pytest.approx(0.3)
    # a disc entirely below the line is empty
    assert clipped_disc_distance(c1 - [0, 2.5, 0], one, c2, one, G, np.array(-1.5), np.array(1.0)) == np.inf


def test_tube_crossings_are_plane_crossings_tube_by_tube(neuro_geometry, needle_geometry):
    """The solver's envelope check asks every tube at once (straight tubes together, helices together): the same
    numbers as plane_crossings tube by tube, for one plane and for many, and a tube of another kind (a helix of
    another length) among them."""
    from chic_register.model.centreline_crossings import plane_crossings, tube_crossings
    from chic_register.model.envelope import plane_normals

    rng = np.random.default_rng(3)
    odd = HelixTube("Hx", "helix", 11.0, 40.0, -3.0, 5.0, 30.0, 2.0)  # fewer brackets than the design's helices
    for tubes in (neuro_geometry.tubes, needle_geometry.tubes + (odd,)):
        for P in (1, 40):
            normals = plane_normals(rng.uniform(0, 89, P), rng.uniform(-180, 180, P)).reshape(-1, 3)
            origins = np.zeros_like(normals)
            origins[:, 2] = rng.uniform(-10, 60, P)
            t, pts, tan, cnt = tube_crossings(tubes, origins, normals)
            for k, tube in enumerate(tubes):
                ref = plane_crossings(tube, origins, normals)
                for got, want in zip((t[:, k], pts[:, k], tan[:, k], cnt[:, k]), ref):
                    np.testing.assert_array_equal(got, want)
            assert (cnt == 1).sum() > P
