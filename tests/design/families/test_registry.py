"""The family registry and the Family interface: every registered family works end to end from its preset spec,
an unknown family is a one-line error, and a new family needs only its own class and one registry entry."""

from __future__ import annotations

import math

import pytest

import chic_register.model.geometry as geometry_mod
from chic_design.cad.parts import CapDims
from chic_design.cli.main import main as design_main
from chic_design.errors import SpecError
from chic_design.families import DEFAULT_FAMILY, FAMILIES, family_named, family_of
from chic_design.families.base import Family, ReportHead
from chic_design.families.chic.cad import RoundCapDims, annulus_blank
from chic_design.families.chic.check import symmetric_pattern_findings
from chic_design.families.sections import CapSpec, ImagingSpec, PrintSpec, Strict, ToolSpec
from chic_design.feasibility.records import Unambiguity
from chic_design.spec import json_schema, parse_spec
from chic_register.model.body import Body
from chic_register.model.tubes import LineTube


def test_the_registry_names_each_family_by_its_own_name():
    assert list(FAMILIES) == ["chic", "zframe", "nlocalizer"] and DEFAULT_FAMILY == "chic"
    for name, family in FAMILIES.items():
        assert isinstance(family, Family) and family.name == name
        assert family.spec_model.model_fields["family"].annotation.__args__ == (name,)


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_family_makes_geometry_check_and_report_head_from_its_preset(name):
    family = FAMILIES[name]
    spec = parse_spec(family.preset, f"{name}-preset.yaml")
    assert family_of(spec) is family and isinstance(spec, family.spec_model)
    geom = family.geometry(spec, source={"spec": "preset"})
    assert geom.family == name and geom.name == spec.name and len(geom.tubes) >= 3
    assert geom.source["generator"].startswith("chic-design ")
    report = family.check(spec)
    assert report.feasible, report.violations
    assert report.tilt_limits[0].depth_mm == 0 and report.tilt_limits[-1].depth_mm == geom.body.length
    schema = json_schema(name)
    assert schema["title"] == f"{family.title} design spec" and "family" in schema["properties"]


@pytest.mark.parametrize("name", list(FAMILIES))
def test_every_family_builds_its_parts_from_its_preset(name):
    family = FAMILIES[name]
    spec = parse_spec(family.preset)
    geom = family.geometry(spec)
    if not family.printed(spec):  # a commercial preset (the Leksell box): described, never printed
        with pytest.raises(ValueError, match="no printed parts"):
            family.parts(spec, geom)
        head = family.report_head(spec, geom, None)
        assert head.title == family.title and all(r.startswith("| ") for r in head.dimension_rows)
        return
    parts = family.parts(spec, geom)
    assert [n for n, _ in parts.items()] == ["body", "cap_top", "cap_bottom"]
    for part_name, part in parts.items():
        assert part.is_valid and len(part.solids()) == 1 and part.label == part_name, part_name
    assert isinstance(parts.cap_dims, CapDims) and parts.cap_dims.thickness == spec.caps.thickness
    bb = parts.body.bounding_box()
    assert bb.min.Z == pytest.approx(0.0, abs=1e-6) and bb.max.Z == pytest.approx(geom.body.length, abs=1e-6)
    head = family.report_head(spec, geom, parts.cap_dims)
    assert isinstance(head, ReportHead) and head.title == family.title
    assert all(r.startswith("| ") and r.endswith(" |") for r in head.dimension_rows)


@pytest.mark.parametrize("value", ["tripod", "", "Chic", ["chic"], {"a": 1}, 3, None])
def test_an_unknown_family_is_a_one_line_error_naming_the_file_and_what_is_allowed(value):
    with pytest.raises(SpecError) as err:
        parse_spec({"family": value, "name": "x"}, "t.yaml")
    assert str(err.value) == f"t.yaml: family: unknown family {value!r}; allowed: chic, zframe, nlocalizer"
    with pytest.raises(SpecError, match=r"^family: unknown family 'tripod'; allowed: chic, zframe, nlocalizer$"):
        json_schema("tripod")
    assert family_named("zframe") is FAMILIES["zframe"]


def test_schema_cli_refuses_an_unknown_family_in_one_line(capsys):
    assert design_main(["schema", "--family", "tripod"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == "chic-design: error: --family: unknown family 'tripod'; allowed: chic, zframe, nlocalizer\n"
    assert design_main(["schema", "--family", "zframe"]) == 0
    assert '"title": "Z-frame fiducial design spec"' in capsys.readouterr().out


def test_a_family_class_must_set_its_attributes():
    with pytest.raises(TypeError, match="family Half does not set spec_model, length_key, preset"):
        class Half(Family):  # noqa: F841 - defined only to be refused
            name = "half"
            title = "half"


# ------------------------------------------------------------------ a new family, in this file only


class TripodRods(Strict):
    diameter: float = 2.0
    radius: float = 10.0
    angles_deg: tuple[float, float, float] = (0.0, 100.0, 220.0)


class TripodSpec(Strict):
    family: str = "tripod"
    name: str
    description: str = ""
    length: float = 40.0
    rods: TripodRods = TripodRods()
    caps: CapSpec = CapSpec()
    print: PrintSpec = PrintSpec()
    imaging: ImagingSpec = ImagingSpec()
    tool: ToolSpec | None = None


class TripodFamily(Family):
    """Three axial rods in a round body: what a new family implements, and nothing more."""

    name = "tripod"
    title = "Tripod fiducial"
    spec_model = TripodSpec
    length_key = "length"
    preset = {"family": "tripod", "name": "tripod"}

    def body(self, spec):
        return Body(spec.length, 30.0, 10.0)

    def tubes(self, spec):
        r = spec.rods.radius
        return tuple(LineTube(f"R{i}", "other", (r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), 0.0),
                              (r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), spec.length),
                              spec.rods.diameter)
                     for i, a in enumerate(spec.rods.angles_deg))

    def parts(self, spec, geometry):
        from chic_design.cad.parts import build_parts

        return build_parts(annulus_blank(geometry), RoundCapDims.from_spec(spec, geometry), geometry)

    def unambiguity(self, geometry, *, usable_ranges_mm, tolerance_mm, symmetries, min_mismatch_mm, helix_crossings):
        unamb = Unambiguity(tolerance_mm, min_mismatch_mm, symmetries, helix_crossings)
        return unamb, symmetric_pattern_findings(symmetries, tolerance_mm), []

    def report_head(self, spec, geometry, cap_dims):
        return ReportHead(self.title, "mm; the body's axis is z", (f"| length | {spec.length:g} mm |",))


@pytest.fixture()
def tripod(monkeypatch):
    """The tripod family registered: one entry in FAMILIES (and the solver's list of geometry families)."""
    family = TripodFamily()
    monkeypatch.setitem(FAMILIES, "tripod", family)
    monkeypatch.setattr(geometry_mod, "FAMILIES", geometry_mod.FAMILIES + ("tripod",))
    return family


def test_a_new_family_is_found_checked_and_reported_through_the_interface(tripod):
    spec = parse_spec({"family": "tripod", "name": "t1", "rods": {"angles_deg": [0.0, 120.0, 240.0]}}, "t.yaml")
    assert family_of(spec) is tripod
    geom = tripod.geometry(spec)
    assert geom.family == "tripod" and geom.ids == ("R0", "R1", "R2")
    report = tripod.check(spec)  # three rods 120 deg apart: its own rule calls that symmetric
    assert "symmetric_pattern" in {v.code for v in report.violations}
    asym = parse_spec(tripod.preset)
    assert "symmetric_pattern" not in {v.code for v in tripod.check(asym).violations}


@pytest.mark.slow
def test_a_new_family_builds_through_the_one_build_path(tripod, tmp_path):
    from chic_design.build.pipeline import build_design

    path = tmp_path / "tripod.yaml"
    path.write_text("family: tripod\nname: tripod\n")
    result = build_design(path, out_root=tmp_path / "exports", progress=False, pictures_in_worker=False)
    assert result.checks.ok
    assert (result.folder / "report.md").read_text().startswith("# Tripod fiducial `tripod`")
    assert "family: tripod" in (result.folder / "geometry.yaml").read_text()
