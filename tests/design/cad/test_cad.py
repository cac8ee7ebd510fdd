"""The CAD model without export: channels follow the geometry objects, analytic volumes and boxes."""

import math
from dataclasses import replace

import numpy as np
import pytest
from build123d import CenterOf, GeomType

from chic_design.cad.channels import blank_volume_mm3, channel_openings_xy, channel_volume_mm3, extended_tube
from chic_design.cad.parts import centreline_edge
from chic_design.families import FAMILIES
from chic_design.families.chic.cad import RoundCapDims
from chic_design.spec import load_spec
from chic_register.model.tubes import HelixTube, LineTube
from tests.conftest import NEEDLE, NEURO

CHIC = FAMILIES["chic"]


@pytest.fixture(scope="module")
def needle():
    spec = load_spec(NEEDLE)
    geom = CHIC.geometry(spec)
    return spec, geom, CHIC.parts(spec, geom)


@pytest.fixture(scope="module")
def neuro():
    spec = load_spec(NEURO)
    geom = CHIC.geometry(spec)
    return spec, geom, CHIC.parts(spec, geom)


LEFT_HELIX = HelixTube("H9", "helix", radius=7.0, theta0_deg=200.0, pitch_deg_per_mm=-3.0,
                       z0=5.0, z1=35.0, diameter=1.5)


@pytest.mark.parametrize("which", ["H0", "H2", "D1", "O0", "left"])
def test_centreline_edge_follows_the_geometry_object(neuro_geometry, which):
    tube = LEFT_HELIX if which == "left" else neuro_geometry.tube(which)
    edge = centreline_edge(tube)
    for u in np.linspace(0, 1, 11):
        p = edge @ u
        want = tube.point_at_z(p.Z)[0]
        assert np.allclose([p.X, p.Y, p.Z], want, atol=1e-6)
    z_lo, z_hi = tube.z_range
    assert (edge @ 0).Z == pytest.approx(z_lo, abs=1e-9)
    assert (edge @ 1).Z == pytest.approx(z_hi, abs=1e-9)


def test_extended_tube_is_the_same_curve_continued(neuro_geometry):
    h = neuro_geometry.tube("H1")
    e = extended_tube(h, 3.0)  # 3 mm of arc length: dz = 3 / sqrt(1 + (r omega)^2) at each end
    dz = 3.0 / math.hypot(1.0, 12.5 * math.radians(h.pitch_deg_per_mm))
    assert (e.z0, e.z1) == pytest.approx((h.z0 - dz, h.z1 + dz))
    assert e.length_mm == pytest.approx(h.length_mm + 6.0)
    z = np.linspace(-2.8, 52.8, 9)
    assert np.allclose(e.point_at_z(z), h.point_at_z(z))
    d = neuro_geometry.tube("D2")
    ed = extended_tube(d, 2.0)
    assert np.allclose(ed.p0, np.add(d.p0, (0, 0, -2))) and np.allclose(ed.p1, np.add(d.p1, (0, 0, 2)))


def test_helix_opening_on_top_face_is_at_theta0_plus_pitch_times_length(neuro_geometry):
    top = channel_openings_xy(neuro_geometry, 50.0)
    for h in neuro_geometry.by_role("helix"):
        a = math.radians(h.theta0_deg + h.pitch_deg_per_mm * 50.0)
        assert np.allclose(top[h.id], [12.5 * math.cos(a), 12.5 * math.sin(a)])
    assert np.allclose(top["D1"], [0.0, 12.5])


def test_channel_volume_hand_worked(neuro_geometry):
    a = 1.5
    assert channel_volume_mm3(neuro_geometry.tube("D0"), 0, 50) == pytest.approx(math.pi * a * a * 50)
    # helix: arc length = L sqrt(1 + (r omega)^2), omega = 1.4 deg/mm in rad/mm
    s = 50 * math.hypot(1, 12.5 * math.radians(1.4))
    assert channel_volume_mm3(neuro_geometry.tube("H0"), 0, 50) == pytest.approx(math.pi * a * a * s)
    assert channel_volume_mm3(neuro_geometry.tube("H0"), 10, 20) == pytest.approx(math.pi * a * a * s / 5)
    assert blank_volume_mm3(neuro_geometry) == pytest.approx(math.pi / 4 * (900 - 400) * 50)


def test_body_volume_is_annulus_minus_channels_needle_guide(needle):
    """needle-guide's channels touch only over 0.25 mm at the ends: the sum is nearly exact."""
    _, geom, parts = needle
    want = blank_volume_mm3(geom) - sum(channel_volume_mm3(t, 0, geom.body.length) for t in geom.tubes)
    assert parts.body.volume == pytest.approx(want, rel=1e-4)


def test_body_volume_neuro_within_channel_overlap(neuro):
    """neuro's helices meet the diametric tubes for ~3 mm at each end; that shared volume is small."""
    _, geom, parts = neuro
    channels = sum(channel_volume_mm3(t, 0, 50) for t in geom.tubes)
    cut = blank_volume_mm3(geom) - parts.body.volume
    assert 0 < channels - cut < 0.01 * channels  # overlap counted twice in the sum, removed once
    one_channel = math.pi * 1.5**2 * 50
    assert channels - cut < 0.1 * one_channel  # not a missing channel


def test_parts_are_single_valid_solids(neuro):
    _, _, parts = neuro
    for name, part in parts.items():
        assert part.is_valid, name
        assert len(part.solids()) == 1, name
        assert part.label == name


def test_bounding_boxes(neuro):
    spec, geom, parts = neuro
    bb = parts.body.bounding_box()
    assert np.allclose([bb.min.X, bb.min.Y, bb.min.Z], [-15, -15, 0], atol=1e-5)
    assert np.allclose([bb.max.X, bb.max.Y, bb.max.Z], [15, 15, 50], atol=1e-5)
    dims = RoundCapDims.from_spec(spec, geom)
    assert dims.outer_radius == pytest.approx(15 + 0.2 + 1.6)
    for end, part in (("top", parts.cap_top), ("bottom", parts.cap_bottom)):
        lo, hi = dims.bbox(50.0, end)
        bb = part.bounding_box()
        assert np.allclose([bb.min.X, bb.min.Y, bb.min.Z], lo, atol=1e-5), end
        assert np.allclose([bb.max.X, bb.max.Y, bb.max.Z], hi, atol=1e-5), end


def test_cap_volumes_hand_worked(neuro):
    spec, geom, parts = neuro
    d = RoundCapDims.from_spec(spec, geom)
    plate = math.pi * (d.outer_radius**2 - d.inner_radius**2) * d.thickness
    skirt = math.pi * (d.outer_radius**2 - d.skirt_inner_radius**2) * d.skirt_height
    ports = len(geom.tubes) * math.pi * (d.port_diameter / 2) ** 2 * d.thickness
    assert parts.cap_bottom.volume == pytest.approx(plate + skirt, rel=1e-6)
    assert parts.cap_top.volume == pytest.approx(plate + skirt - ports, rel=1e-6)


def test_top_cap_ports_sit_over_the_tube_end_points(neuro):
    spec, geom, parts = neuro
    t = spec.caps.thickness
    r_port = spec.caps.fill_port_diameter / 2
    holes = [f for f in parts.cap_top.faces() if f.geom_type == GeomType.CYLINDER
             and f.radius == pytest.approx(r_port)]
    centres = np.array([[f.center(CenterOf.MASS).X, f.center(CenterOf.MASS).Y] for f in holes])
    assert len(centres) == len(geom.tubes)
    for tube in geom.tubes:
        end = tube.point_at_z(50.0)[0]
        assert np.min(np.linalg.norm(centres - end[:2], axis=1)) < 1e-6, tube.id
        x, y = end[:2]
        assert not parts.cap_top.is_inside((x, y, 50 + t / 2))  # open over the channel
        assert parts.cap_bottom.is_inside((x, y, -t / 2))  # the bottom cap seals it


def test_channels_run_through_the_body(neuro):
    """No material on any centreline near both end faces and at mid height; material between channels."""
    _, geom, parts = neuro
    for tube in geom.tubes:
        for z in (0.2, 25.0, 49.8):
            p = tube.point_at_z(z)[0]
            assert not parts.body.is_inside(tuple(p)), (tube.id, z)
    # material between two channels at mid height
    d0, o1 = geom.tube("D0").point_at_z(25.0)[0], geom.tube("O1").point_at_z(25.0)[0]
    mid = (d0 + o1) / 2
    mid[:2] *= 12.5 / np.linalg.norm(mid[:2])
    assert parts.body.is_inside(tuple(mid))


def test_caps_only_touch_the_body(neuro):
    _, _, parts = neuro
    for cap in (parts.cap_top, parts.cap_bottom):
        common = parts.body.intersect(cap)
        assert common is None or common.volume < 1e-6


def test_shifted_tube_changes_the_body(neuro_geometry):
    """Sanity: the body is made from the tubes given (a moved tube moves its channel)."""
    d0 = neuro_geometry.tube("D0")
    moved = LineTube("D0", "diametric", np.add(d0.p0, (0, 0.5, 0)), np.add(d0.p1, (0, 0.5, 0)), d0.diameter)
    geom = replace(neuro_geometry, tubes=(moved,) + neuro_geometry.tubes[1:])
    spec = load_spec(NEURO)
    body = CHIC.parts(spec, geom).body
    assert not body.is_inside((12.5, 0.5, 25.0))
    assert body.is_inside((12.5, -1.3, 25.0))
