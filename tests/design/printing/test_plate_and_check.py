"""The print stage without a slicer: settings from the design, the plate's layout and its 3MF round trip, the
G-code reader, and the channel check on hand-made toolpaths whose answers are worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from chic_design.cli.main import main
from chic_design.errors import PrintFileError, SpecError
from chic_design.families import family_named
from chic_design.printing.check import (
    CheckedChannel,
    LayerMeasure,
    PrintCheck,
    bead_width_mm,
    check_channels,
    measure_channel,
    toolpath_scale,
)
from chic_design.printing.export import scale_text, scan_calibration
from chic_design.printing.limits import MAX_OVERHANG_SHARE
from chic_design.printing.plate import Placement, make_plate, read_plate, seam_angle_deg, write_plate
from chic_design.printing.settings import auto_layer_mm, print_settings, prusa_config
from chic_design.printing.toolpaths import KIND_CODE, Layer, read_toolpaths
from chic_design.spec import parse_spec
from chic_register.model.geometry import content_sha256, scaled_geometry, write_geometry
from chic_register.model.tubes import LineTube


def _zframe():
    fam = family_named("zframe")
    spec = fam.spec_model.model_validate(fam.preset)
    return spec, fam.geometry(spec)


def test_layer_height_is_a_tenth_of_the_smallest_channel_within_the_nozzle_range():
    assert auto_layer_mm(1.6, 0.4) == pytest.approx(0.16)
    assert auto_layer_mm(3.0, 0.4) == pytest.approx(0.2)    # capped at half the nozzle
    assert auto_layer_mm(0.6, 0.4) == pytest.approx(0.1)    # floored at a quarter of it
    assert auto_layer_mm(0.6, 0.8) == pytest.approx(0.2)


def test_printer_keys_are_validated_with_one_line_messages():
    spec, _ = _zframe()
    data = {**_zframe_preset(), "print": {"printer": "sla"}}
    with pytest.raises(SpecError, match=r"print.printer: .*'fdm' or 'resin'"):
        parse_spec(data, "x.yaml")
    data = {**_zframe_preset(), "print": {"layer_height": 0.4}}
    with pytest.raises(SpecError, match=r"layer_height \(0.4\) must be at most 0.8 x nozzle_diameter"):
        parse_spec(data, "x.yaml")


def _zframe_preset():
    return dict(family_named("zframe").preset)


def test_resin_plates_carry_an_sla_profile_and_fdm_plates_solid_walls_without_supports():
    spec, geom = _zframe()
    fdm = prusa_config(print_settings(spec, geom))
    assert fdm["printer_technology"] == "FFF" and fdm["fill_density"] == "100%" and fdm["support_material"] == "0"
    assert fdm["layer_height"] == "0.2" and fdm["perimeters"] == "3" and fdm["seam_position"] == "rear"
    resin = parse_spec({**_zframe_preset(), "print": {"printer": "resin"}}, "x.yaml")
    sla = prusa_config(print_settings(resin, geom))
    assert sla["printer_technology"] == "SLA" and sla["supports_enable"] == "0" and sla["layer_height"] == "0.05"


def test_the_zframe_seam_faces_its_face_without_a_diagonal():
    """z001 has diagonals on +x, +y and -x: the -y face's middle (270 deg) is 45 deg from the nearest rod."""
    _, geom = _zframe()
    assert seam_angle_deg(geom) == pytest.approx(270.0)


def _boxes(geom):
    """Stand-ins for the three parts: the body's box and two cap-sized plates, in F (cap_top above the body)."""
    s, L = geom.body.outer_side / 2, geom.body.length
    body = trimesh.creation.box(bounds=[(-s, -s, 0), (s, s, L)])
    top = trimesh.creation.box(bounds=[(-s - 2, -s - 2, L - 4), (s + 2, s + 2, L + 2)])
    bottom = trimesh.creation.box(bounds=[(-s - 2, -s - 2, -2), (s + 2, s + 2, 4)])
    meshes = {"body": body.vertices, "cap_top": top.vertices, "cap_bottom": bottom.vertices}
    faces = {"body": body.faces, "cap_top": top.faces, "cap_bottom": bottom.faces}
    return meshes, faces


def test_plate_round_trips_and_an_independent_reader_places_every_part_on_the_bed(tmp_path):
    spec, geom = _zframe()
    meshes, faces = _boxes(geom)
    plate = make_plate(meshes, geom, print_settings(spec, geom), {"design": "zframe"})
    path = write_plate(tmp_path / "plate.3mf", plate, meshes, faces, "zframe")
    back = read_plate(path)
    assert [p.name for p in back.placements] == ["body", "cap_top", "cap_bottom"]
    for a, b in zip(plate.placements, back.placements):
        np.testing.assert_allclose(a.T_bed_from_F, b.T_bed_from_F, atol=1e-6)
    assert back.config["layer_height"] == "0.2" and back.info["design"] == "zframe" and back.fits_bed
    scene = trimesh.load(path)  # trimesh's own 3MF reader applies the build items' transforms
    boxes = []
    for name, p in zip(("body", "cap_top", "cap_bottom"), back.placements):
        placed = p.to_bed(meshes[name])
        assert placed[:, 2].min() == pytest.approx(0.0, abs=1e-6)           # on the bed
        assert placed[:, 0].min() >= 0 and placed[:, 0].max() <= plate.bed_mm[0]
        assert placed[:, 1].min() >= 0 and placed[:, 1].max() <= plate.bed_mm[1]
        boxes.append((placed.min(axis=0), placed.max(axis=0)))
    for i in range(3):
        for j in range(i + 1, 3):  # footprints apart
            (lo1, hi1), (lo2, hi2) = boxes[i], boxes[j]
            assert hi1[0] <= lo2[0] or hi2[0] <= lo1[0] or hi1[1] <= lo2[1] or hi2[1] <= lo1[1]
    got = np.sort(np.concatenate([g.bounds for g in scene.dump()]).reshape(-1, 3), axis=0)
    want = np.sort(np.concatenate(boxes).reshape(-1, 3), axis=0)
    np.testing.assert_allclose(got, want, atol=1e-4)
    top = back.placement("cap_top")
    assert top.T_bed_from_F[2, 2] == pytest.approx(-1.0)  # turned over: the plate (top in F) goes down


GCODE = """\
M82 ; absolute extrusion
G92 E0
;LAYER_CHANGE
;Z:0.2
;HEIGHT:0.2
G1 Z.2
G1 X0 Y0 F7800
;TYPE:External perimeter
;WIDTH:0.45
G1 X10 Y0 E1.0
G1 X10 Y10 E2.0
G1 X0 Y10 F7800
G1 E1.5 ; retract: no segment
G92 E0
;TYPE:Solid infill
;WIDTH:0.5
G1 X5 Y5 E0.5
;LAYER_CHANGE
;Z:0.4
;HEIGHT:0.2
M83 ; relative extrusion
G1 X6 Y5 E0.1
G1 X7 Y5 E-0.1
G1 X8 Y5 E0.2
"""


def test_gcode_reader_keeps_extrusions_with_their_width_and_kind(tmp_path):
    path = tmp_path / "t.gcode"
    path.write_text(GCODE)
    layers = read_toolpaths(path)
    assert [(lay.z_mm, lay.height_mm) for lay in layers] == [(0.2, 0.2), (0.4, 0.2)]
    np.testing.assert_allclose(layers[0].segments_mm, [[0, 0, 10, 0], [10, 0, 10, 10], [0, 10, 5, 5]])
    np.testing.assert_allclose(layers[0].width_mm, [0.45, 0.45, 0.5])
    assert list(layers[0].kind) == [KIND_CODE["External perimeter"]] * 2 + [KIND_CODE["Solid infill"]]
    np.testing.assert_allclose(layers[1].segments_mm, [[5, 5, 6, 5], [7, 5, 8, 5]])  # the retracting move is none


def _ring_layer(z_top_mm, h_mm, centre, hole_d_mm, width_mm=0.45, loops=3, extra=()):
    """Perimeter loops round a hole of ``hole_d_mm`` as the slicer spaces them, plus ``extra`` segments."""
    spacing = float(bead_width_mm(width_mm, h_mm))
    segs = []
    for k in range(loops):
        r = hole_d_mm / 2 + spacing / 2 + k * spacing
        phi = np.linspace(0, 2 * np.pi, 97)
        pts = np.c_[centre[0] + r * np.cos(phi), centre[1] + r * np.sin(phi)]
        segs += [(*pts[i], *pts[i + 1]) for i in range(len(pts) - 1)]
    segs += list(extra)
    n = len(segs)
    return Layer(z_top_mm, h_mm, np.asarray(segs, float), np.full(n, width_mm), np.zeros(n, np.int8))


def test_an_open_ring_passes_and_a_bead_across_the_hole_is_named_with_its_layer():
    tube = LineTube("A0", "axial", (0, 0, 0), (0, 0, 2), 3.0)
    ch = CheckedChannel("A0", "body", tube)
    place = {"body": Placement("body", np.eye(4) + np.pad(np.array([[0, 0, 0, 50], [0, 0, 0, 60], [0, 0, 0, 0]]),
                                                           ((0, 1), (0, 0))))}
    layers = [_ring_layer(0.2 * (k + 1), 0.2, (50, 60), 3.0) for k in range(9)]
    ok = check_channels([ch], place, layers, 0.45, 0.2, nozzle_mm=0.4)
    assert ok.ok and ok.channels[0].layers == 9
    assert ok.channels[0].min_clear_mm == pytest.approx(3.0, abs=0.03)
    assert ok.channels[0].max_offset_mm < 0.01
    across = [(48.0, 60.0, 52.0, 60.0)]  # one 0.45 mm bead straight through the hole's middle, at z = 1.0
    layers[4] = _ring_layer(1.0, 0.2, (50, 60), 3.0, extra=across)
    bad = check_channels([ch], place, layers, 0.45, 0.2, nozzle_mm=0.4)
    c = bad.channels[0]
    assert not bad.ok and c.worst_z_mm == pytest.approx(1.0)
    # the bead (flat width 0.45 - 0.2 (1 - pi/4) = 0.407 mm) leaves two halves of (3 - 0.407) / 2 = 1.30 mm
    assert c.min_clear_mm == pytest.approx((3.0 - 0.407) / 2, abs=0.03)
    assert "narrowed" in c.problems[0] and "z = 1 mm" in c.problems[0]
    assert "A0 (body)" in bad.failure_text()


def _raster_layer(z_top_mm, h_mm, cx_mm, a_mm, b_mm, width_mm=0.45):
    """Solid rows of beads (spaced as the slicer spaces them) everywhere but an ellipse of semi-axes a (x), b (y)
    round (cx, 0): each row stops where its round end cap touches the ellipse."""
    spacing = float(bead_width_mm(width_mm, h_mm))
    r = spacing / 2
    segs = []
    for y in np.arange(-6.0, 6.0 + 1e-9, spacing / 4):
        near = max(abs(y) - r, 0.0)  # the row's bead edge nearest the ellipse's axis
        if near >= b_mm:
            segs.append((cx_mm - 8, y, cx_mm + 8, y))
            continue
        half = a_mm * math.sqrt(1 - (near / b_mm) ** 2)
        segs += [(cx_mm - 8, y, cx_mm - half - r, y), (cx_mm + half + r, y, cx_mm + 8, y)]
    n = len(segs)
    return Layer(z_top_mm, h_mm, np.asarray(segs, float), np.full(n, width_mm), np.zeros(n, np.int8))


@pytest.mark.parametrize("h_mm, fails", [(0.2, False), (0.3, True)])
def test_an_inclined_channel_overhangs_each_layer_by_h_tan_beta(h_mm, fails):
    """A channel 45 deg from vertical: each layer's opening (an ellipse 3/cos 45 long) moves h tan 45 = h along x,
    so the beads round it overhang the opening below by h. Against half a 0.45 mm bead: 0.2 mm prints, 0.3 sags."""
    tube = LineTube("Z", "diagonal", (0, 0, 0), (3, 0, 3), 3.0)
    ch = CheckedChannel("Z", "body", tube)
    place = {"body": Placement("body", np.eye(4))}
    a, b = 1.5 / math.cos(math.radians(45)), 1.5
    layers = [_raster_layer(h_mm * (k + 1), h_mm, h_mm * (k + 0.5), a, b) for k in range(int(2.0 / h_mm))]
    m = measure_channel(ch, place["body"], layers, 0.45)
    assert np.median([v.overhang_mm for v in m[1:]]) == pytest.approx(h_mm, abs=0.03)
    assert min(v.clear_mm for v in m) == pytest.approx(3.0, abs=0.1)
    res = check_channels([ch], place, layers, 0.45, h_mm, nozzle_mm=0.4)
    assert res.ok is not fails
    if fails:
        assert "overhang" in res.channels[0].problems[0] and res.channels[0].overhang_mm > MAX_OVERHANG_SHARE * 0.45


def test_a_scan_calibration_is_set_beside_the_toolpaths_scale(tmp_path):
    """A geometry file from `chic-register calibrate` (here: the Z-frame scaled by 1.004) is read for its factor;
    against toolpaths at scale 1.000 the report says the print and scanner add +0.40 %."""
    _, geom = _zframe()
    path = write_geometry(scaled_geometry(geom, 1.004, {"factor": 1.004, "factor_sd": 0.0005}), tmp_path / "g2.yaml")
    scan = scan_calibration(path)
    assert scan["factor"] == pytest.approx(1.004)
    result = PrintCheck((), 0.45, 0.2, "", 10, 0.4, toolpath_scale=1.0, toolpath_scale_sd=0.0001)
    assert "+0.40% beyond the toolpaths" in scale_text(result, scan)
    plain = write_geometry(geom, tmp_path / "g.yaml")
    with pytest.raises(PrintFileError, match="no calibration in its source"):
        scan_calibration(plain)


def test_toolpath_scale_is_the_least_squares_ratio_of_centres():
    ms = [LayerMeasure(0.2, 1.0, 3.0, (0.003 * x, 0.003 * y), 0.0, (x, y)) for x, y in [(10, 0), (0, 12), (-9, 3)]]
    s, sd = toolpath_scale(ms)
    assert s == pytest.approx(1.003) and sd == pytest.approx(0.0, abs=1e-9)


def _export_with_plate(tmp_path):
    spec, geom = _zframe()
    folder = tmp_path / "zframe"
    folder.mkdir()
    write_geometry(geom, folder / "geometry.yaml")
    meshes, faces = _boxes(geom)
    info = {"geometry_sha256": content_sha256(geom.content())}
    write_plate(folder / "plate.3mf", make_plate(meshes, geom, print_settings(spec, geom), info), meshes, faces, "z")
    return folder, geom


def test_printcheck_refuses_what_it_cannot_check_in_one_line(tmp_path, capsys):
    folder, geom = _export_with_plate(tmp_path)
    cases = [
        ([str(tmp_path / "nowhere")], 2, "no such export folder"),
        ([str(folder), "--slicer", str(tmp_path / "no-slicer")], 3, "cannot run the slicer"),
    ]
    for argv, code, text in cases:
        assert main(["printcheck", *argv, "--quiet"]) == code
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0], err
    write_geometry(scaled_geometry(geom, 1.01, {"factor": 1.01}), folder / "geometry.yaml")
    assert main(["printcheck", str(folder), "--quiet"]) == 2
    assert "laid out for another geometry.yaml" in capsys.readouterr().err
    (folder / "plate.3mf").unlink()
    assert main(["printcheck", str(folder), "--quiet"]) == 2
    assert "no such plate" in capsys.readouterr().err
    assert not (folder / "printcheck.json").exists()


def test_an_opening_in_empty_space_is_not_a_pass():
    """Toolpaths 20 mm away from where the plate puts the part: every section is 'open', but nothing walls it in."""
    tube = LineTube("A0", "axial", (0, 0, 0), (0, 0, 2), 3.0)
    ch = CheckedChannel("A0", "body", tube)
    place = {"body": Placement("body", np.eye(4))}
    layers = [_ring_layer(0.2 * (k + 1), 0.2, (20.0, 0.0), 3.0) for k in range(9)]
    res = check_channels([ch], place, layers, 0.45, 0.2, nozzle_mm=0.4)
    assert not res.ok and "not walled in" in res.channels[0].problems[0]
    assert res.channels[0].wall_share == pytest.approx(0.0)
