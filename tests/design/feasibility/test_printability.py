"""check == build: what build cannot make is a violation check reports, and build refuses it even forced."""

from __future__ import annotations

import math

import pytest
import yaml

from chic_design.build.pipeline import build_design
from chic_design.errors import InfeasibleDesign
from chic_design.families import FAMILIES
from chic_design.feasibility.printability import HARD_CODES, MAX_DEPTH_SIGMA_MM, build_violations
from chic_design.spec import parse_spec
from tests.conftest import NEURO, ZFRAME

CHIC = FAMILIES["chic"]


def _spec(**edits):
    data = yaml.safe_load(NEURO.read_text())
    for dotted, value in edits.items():
        section, key = dotted.split("__")
        data[section][key] = value
    return parse_spec(data)


def _codes(spec):
    return {f.code: f for f in build_violations(spec, CHIC.geometry(spec), spec.imaging.pixel_size, CHIC.length_key)}


def test_the_repository_designs_have_none():
    assert _codes(_spec()) == {}


@pytest.mark.parametrize("edits, code, where", [
    ({"caps__skirt_height": 25.0}, "caps_meet", "caps.skirt_height"),       # skirts of 2 x 25 mm on a 50 mm body
    ({"caps__thickness": 0.3}, "cap_wall_too_thin", "caps.thickness"),    # print.min_wall applies to the caps
    ({"caps__skirt_wall": 0.5}, "cap_wall_too_thin", "caps.skirt_wall"),
    # 0.2 mm walls on both sides of 3 mm channels: thicker than min_wall, but no clear section to check
    ({"body__inner_diameter": 21.6, "body__outer_diameter": 28.4, "print__min_wall": 0.15}, "no_clear_section",
     "all depths"),
    ({"helix__offset_deg": 44.99}, "depth_imprecise", "helix"),          # a depth sigma of 955 mm
])
def test_each_rule(edits, code, where):
    found = _codes(_spec(**edits))
    assert list(found) == [code]
    assert found[code].where == where


def test_depth_precision_figure_is_the_reports():
    """44.99 deg: pitch (90 - 2 x 44.99) / 50 deg/mm; sigma_z = (0.5/sqrt(12)/12.5 rad in deg) / pitch / sqrt(3)."""
    pitch = (90 - 2 * 44.99) / 50
    sigma = math.degrees(0.5 / math.sqrt(12) / 12.5) / pitch / math.sqrt(3)
    assert sigma > 900
    msg = _codes(_spec(helix__offset_deg=44.99))["depth_imprecise"].message
    assert f"{sigma:.3g} mm" in msg and f"at most {MAX_DEPTH_SIGMA_MM:g} mm" in msg
    # a pitch that still encodes depth usefully passes: 30 deg offset, 0.6 deg/mm, sigma 0.63 mm
    assert "depth_imprecise" not in _codes(_spec(helix__offset_deg=30.0))


def test_check_reports_them_and_build_refuses_even_with_force(tmp_path):
    path = tmp_path / "spec.yaml"
    data = yaml.safe_load(NEURO.read_text())
    data["caps"]["thickness"] = 0.3
    data["helix"]["offset_deg"] = 44.99
    path.write_text(yaml.safe_dump(data))
    report = CHIC.check(parse_spec(data))
    assert not report.feasible
    assert {"cap_wall_too_thin", "depth_imprecise"} <= {v.code for v in report.violations}
    assert {v["code"] for v in report.to_dict()["violations"]} >= {"cap_wall_too_thin", "depth_imprecise"}
    with pytest.raises(InfeasibleDesign, match="--force cannot build it") as err:
        build_design(path, out_root=tmp_path / "exports", force=True, progress=False, pictures_in_worker=False)
    assert {v.code for v in err.value.violations} <= HARD_CODES
    assert not any((tmp_path / "exports").iterdir())


@pytest.mark.parametrize("path, family, key", [(NEURO, "chic", "body.length"), (ZFRAME, "zframe", "frame.height")])
def test_messages_name_the_familys_own_length_key(path, family, key):
    data = yaml.safe_load(path.read_text())
    data["caps"]["skirt_height"] = 30.0
    spec = parse_spec(data)
    fam = FAMILIES[family]
    found = {f.code: f for f in build_violations(spec, fam.geometry(spec), spec.imaging.pixel_size, fam.length_key)}
    assert f"must be less than half of {key} (" in found["caps_meet"].message
