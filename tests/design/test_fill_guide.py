"""The fill guide: ports and connected channel groups worked out by hand for the Z-frame and CHIC presets,
volumes, the sealing order, and the three files (the PDF rendered back to an image)."""

import base64
import math
import re

import numpy as np
import pypdfium2 as pdfium
import pytest
from PIL import Image

from chic_design.cad.channels import channel_volume_mm3
from chic_design.families import family_named
from chic_design.families.chic.cad import RoundCapDims
from chic_design.families.zframe.cad import SquareCapDims
from chic_design.report.fill_guide import (
    FILL_GUIDE_FILES,
    connected_groups,
    fill_guide,
    fill_guide_markdown,
    needle_for,
    write_fill_guide,
)
from chic_design.spec import load_spec
from tests.conftest import NEEDLE

A4_PT = (595.44, 841.68)  # 8.27 x 11.69 in at 72 pt/in


def preset(name, dims_type):
    fam = family_named(name)
    spec = fam.spec_model.model_validate(fam.preset)
    geom = fam.geometry(spec)
    return geom, dims_type.from_spec(spec, geom)


@pytest.fixture(scope="module")
def zframe():
    geom, dims = preset("zframe", SquareCapDims)
    return geom, dims, fill_guide(geom, dims)


@pytest.fixture(scope="module")
def chic():
    geom, dims = preset("chic", RoundCapDims)
    return geom, dims, fill_guide(geom, dims)


def test_zframe_has_four_corner_ports_each_over_a_rod_and_the_diagonal_ending_there(zframe):
    """Rods A0..A3 stand at the corners (+30, -30), (+30, +30), (-30, +30), (-30, -30); diagonal Z+x runs from
    A1's foot up to A0's top, Z+y from A2's foot to A1's top, Z-x from A3's foot to A2's top. So the top face
    has four openings: A0 with Z+x, A1 with Z+y, A2 with Z-x, and A3 alone."""
    _, _, guide = zframe
    got = [(p.number, round(p.x_mm, 6), round(p.y_mm, 6), p.channel_ids) for p in guide.ports]
    assert got == [(1, 30.0, -30.0, ("A0", "Z+x")), (2, 30.0, 30.0, ("A1", "Z+y")),
                   (3, -30.0, 30.0, ("A2", "Z-x")), (4, -30.0, -30.0, ("A3",))]


def test_zframe_rods_are_one_network_filled_from_the_lone_rod(zframe):
    """Top openings join A0-Z+x, A1-Z+y, A2-Z-x; bottom openings (under the bottom cap) join Z+x-A1, Z+y-A2,
    Z-x-A3: one chain A0 . Z+x . A1 . Z+y . A2 . Z-x . A3 through all four ports. Every port has a 60 mm rod;
    port 4 opens onto that rod alone, so the fluid runs one way: inject there, the other three vent."""
    geom, _, guide = zframe
    assert len(guide.groups) == 1
    g = guide.groups[0]
    assert set(g.channel_ids) == {"A0", "A1", "A2", "A3", "Z+x", "Z+y", "Z-x"}
    assert g.port_numbers == (1, 2, 3, 4)
    assert g.fill_port == 4 and g.vent_ports == (1, 2, 3)
    assert guide.seal_order == (1, 2, 3, 4)  # vents first, the fill port last
    # by hand: four 60 mm rods and three diagonals of sqrt(60^2 + 60^2) mm, 3 mm across
    area = math.pi * 1.5 ** 2
    assert g.volume_mm3 == pytest.approx(area * (4 * 60 + 3 * math.hypot(60, 60)), rel=1e-9)
    assert g.volume_mm3 == pytest.approx(sum(channel_volume_mm3(t, 0, 60.0) for t in geom.tubes), rel=1e-12)
    joints = " ".join(g.joints)
    for a, b in (("Z+x", "A1"), ("Z+y", "A2"), ("Z-x", "A3")):
        assert f"{a} and {b}: one opening at the bottom" in joints


def test_chic_has_a_port_per_channel_and_the_helices_join_the_diametric_channels(chic):
    """No two CHIC channels share an opening: nine ports in tube order. Each helix touches the diametric channel
    it starts beside (near z = 0) and the next one (near z = length): D0-H0-D1-H1-D2-H2-D3 is one group,
    each orientation channel is a group of its own."""
    geom, _, guide = chic
    assert [p.channel_ids for p in guide.ports] == [(t,) for t in geom.ids]
    assert [p.number for p in guide.ports] == list(range(1, 10))
    for p, t in zip(guide.ports, geom.tubes):
        assert np.allclose([p.x_mm, p.y_mm], t.point_at_z(geom.body.length)[0, :2])
    groups = [(g.channel_ids, g.port_numbers, g.fill_port, g.vent_ports) for g in guide.groups]
    assert groups == [(("D0", "D1", "D2", "D3", "H0", "H1", "H2"), (1, 2, 3, 4, 5, 6, 7), 1, (2, 3, 4, 5, 6, 7)),
                      (("O0",), (8,), 8, ()), (("O1",), (9,), 9, ())]
    assert guide.seal_order == (2, 3, 4, 5, 6, 7, 1, 8, 9)
    tubes = {t.id: t for t in geom.tubes}
    for g in guide.groups:
        assert g.volume_mm3 == pytest.approx(sum(channel_volume_mm3(tubes[i], 0, 50.0) for i in g.channel_ids))
    assert guide.total_volume_mm3 == pytest.approx(sum(channel_volume_mm3(t, 0, 50.0) for t in geom.tubes))
    assert "D0 and H0: touch in the wall at z 0.0..2.9 mm" in guide.groups[0].joints


def test_union_find_joins_chains_and_keeps_tube_order():
    assert connected_groups(["a", "b", "c", "d", "e"], [("d", "b"), ("e", "d")]) == [("a",), ("b", "d", "e"), ("c",)]
    assert connected_groups(["a", "b"], []) == [("a",), ("b",)]


def test_needle_leaves_room_for_air_in_the_port():
    assert needle_for(1.2) == (25, 0.51)
    assert needle_for(0.8) == (30, 0.31)
    assert needle_for(0.3) is None


def test_a_cap_without_ports_is_filled_before_it_goes_on():
    geom, dims = preset("chic", RoundCapDims)
    fam = family_named("chic")
    spec = fam.spec_model.model_validate({**fam.preset, "caps": {**fam.preset.get("caps", {}),
                                                                   "fill_port_diameter": 0}})
    guide = fill_guide(geom, RoundCapDims.from_spec(spec, geom))
    assert not guide.has_ports and guide.needle_gauge is None
    text = " ".join(guide.procedure)
    assert "no ports: fill before it goes on" in text and "Seal the ports" not in text


def test_the_markdown_section_has_the_tables_steps_and_links(chic):
    _, dims, guide = chic
    text = fill_guide_markdown(guide)
    assert text.startswith("## Filling and closing\n")
    for name in FILL_GUIDE_FILES:
        assert f"({name})" in text
    assert "| 9 | 10.83 | -6.25 | O1 | 3 | fill |" in text
    assert f"| 1 | D0, D1, D2, D3, H0, H1, H2 | 1, 2, 3, 4, 5, 6, 7 | 1 | 2, 3, 4, 5, 6, 7 | " \
           f"{guide.groups[0].volume_ml:.3f} |" in text
    assert "Seal the ports in this order: 2, 3, 4, 5, 6, 7, 1, 8, 9" in text
    assert f"{dims.clearance:g} mm radial clearance" in text and "25 G" in text
    assert "missing_tubes" in text and "dark gap" in text
    steps = re.findall(r"^(\d+)\. ", text, flags=re.M)
    assert steps == [str(k) for k in range(1, len(guide.procedure) + 1)]


def test_the_three_files_are_written_and_the_pdf_renders_the_picture(zframe, tmp_path):
    _, _, guide = zframe
    assert write_fill_guide(guide, tmp_path) == list(FILL_GUIDE_FILES)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(FILL_GUIDE_FILES)  # no temporary left
    png = (tmp_path / "fill_guide.png").read_bytes()
    page = (tmp_path / "fill_guide.html").read_text(encoding="utf-8")
    assert base64.b64encode(png).decode("ascii") in page  # self-contained: the picture inside
    assert "<td>A0, Z+x</td>" in page and "Seal the ports in this order" in page
    pdf = pdfium.PdfDocument(tmp_path / "fill_guide.pdf")
    assert 1 <= len(pdf) <= 2
    for k in range(len(pdf)):
        assert pdf[k].get_size() == pytest.approx(A4_PT, abs=1.0)
    img = np.asarray(pdf[0].render(scale=1.0).to_pil().convert("RGB")).astype(int)
    assert abs(img.shape[0] - A4_PT[1]) <= 1 and abs(img.shape[1] - A4_PT[0]) <= 1  # 1 px per pt
    ink = (img < 200).any(axis=2)
    assert ink.mean() > 0.01  # not blank
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    blue = (b > 150) & (r < 80) & (g > 80) & (g < 160)  # tab10's first colour: the one group's ports and labels
    rows, cols = np.nonzero(blue)
    assert blue.sum() > 100
    assert rows.min() > 0.04 * img.shape[0] and rows.max() < 0.55 * img.shape[0]  # in the picture, page top half
    grey = (np.abs(r - 235) < 4) & (np.abs(g - 235) < 4) & (np.abs(b - 235) < 4)  # the cap's plate
    assert grey.sum() > 5000
    text = pdf[1].get_textpage().get_text_range()
    assert "Procedure" in text and "Seal the ports in this order: 1, 2, 3, 4" in text


def test_the_png_shows_every_port_in_its_group_colour(chic, tmp_path):
    _, _, guide = chic
    write_fill_guide(guide, tmp_path)
    img = np.asarray(Image.open(tmp_path / "fill_guide.png").convert("RGB")).astype(int)
    assert img.shape[0] > 500 and img.shape[1] > 800
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    orange = (r > 220) & (g > 100) & (g < 150) & (b < 60)  # group 2 (O0)
    green = (g > 130) & (r < 80) & (b < 80)  # group 3 (O1)
    assert orange.sum() > 30 and green.sum() > 30


def test_the_needle_guide_design_fills_with_a_thinner_needle(tmp_path):
    spec = load_spec(NEEDLE)
    fam = family_named("chic")
    geom = fam.geometry(spec)
    guide = fill_guide(geom, RoundCapDims.from_spec(spec, geom))
    assert guide.port_diameter_mm == 0.8 and guide.needle_gauge == 30
    assert len(guide.ports) == len(geom.tubes) == 9


def test_a_resin_print_s_vent_grooves_are_glued_shut_with_the_bottom_cap():
    geom, dims = preset("chic", RoundCapDims)
    plain = fill_guide(geom, dims)
    resin = fill_guide(geom, dims, vent_grooves=True)
    assert "plate.3mf" in plain.procedure[0]
    assert not any("vent grooves" in s for s in plain.procedure)
    assert "Work the glue into the vent grooves" in resin.procedure[2]
