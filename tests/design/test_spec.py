"""Spec validation: good specs load, each kind of mistake gets its own one-line message."""

import json

import pytest
import yaml

from chic_design.cli.main import main
from chic_design.errors import SpecError
from chic_design.families import FAMILIES
from chic_design.spec import json_schema, load_spec
from tests.conftest import NEEDLE, NEURO


def test_designs_load_with_paper_values():
    spec = load_spec(NEURO)
    assert (spec.body.length, spec.body.outer_diameter, spec.body.inner_diameter) == (50, 30, 20)
    assert spec.channels.diameter == 3
    assert spec.channel_radius == 12.5  # default: middle of the wall
    assert spec.helix.offset_deg == 10
    slim = load_spec(NEEDLE)
    assert slim.body.outer_diameter <= 16


def test_default_pitch_runs_offset_to_quadrant_minus_offset(neuro_spec):
    geom = FAMILIES["chic"].geometry(neuro_spec)
    for k, h in enumerate(geom.by_role("helix")):
        q = neuro_spec.markers.helix_quadrants[k]
        assert h.pitch_deg_per_mm == pytest.approx(70 / 50)  # the paper's omega = 1.4 deg/mm
        assert h.angle_deg_at(0) == pytest.approx(90 * q + 10)
        assert h.angle_deg_at(50) == pytest.approx(90 * q + 80)


def _write(tmp_path, data, name="spec.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return p


def _neuro_dict():
    return yaml.safe_load(NEURO.read_text())


def _mutate(path_keys, value):
    d = _neuro_dict()
    node = d
    for k in path_keys[:-1]:
        node = node[k]
    if value is KeyError:
        del node[path_keys[-1]]
    else:
        node[path_keys[-1]] = value
    return d


BAD = [
    (_mutate(["body", "lenght"], 5), ["unknown key 'body.lenght'", "allowed keys here: length"]),
    (_mutate(["body", "length"], "long"), ["body.length", "valid number", "'long'"]),
    (_mutate(["body", "length"], -5), ["body.length", "greater than or equal to 2"]),
    (_mutate(["body", "outer_diameter"], KeyError), ["missing key 'body.outer_diameter'"]),
    (_mutate(["body", "inner_diameter"], 32), ["inner_diameter (32) must be smaller than outer_diameter (30)"]),
    (_mutate(["channels", "diameter"], 6), ["do not fit in the wall"]),
    (_mutate(["helix", "offset_top_deg"], 5) | {"helix": {"offset_deg": 10, "offset_top_deg": 5, "pitch_deg_per_mm": 1.0}},
     ["either pitch_deg_per_mm or offset_top_deg"]),
    (_mutate(["markers", "diametric_deg"], [10, 90, 180, 270]), ["diametric_deg[0] must be 0"]),
    (_mutate(["markers", "orientation_deg"], [45]), ["orientation tube at 45 deg is outside the free quadrant 3"]),
    (_mutate(["markers", "helix_quadrants"], [0, 0, 1]), ["3 different quadrants"]),
    (_mutate(["imaging", "pixel_size"], -1), ["imaging.pixel_size", "greater than or equal to 0"]),
    (_mutate(["name"], "my design!"), ["name", "should match pattern"]),
    (_mutate(["caps", "fill_port_diameter"], 3.5), ["fill_port_diameter (3.5) must be smaller"]),
]


@pytest.mark.parametrize("data,expected", BAD, ids=[e[0] for _, e in BAD])
def test_bad_specs_are_rejected_with_one_line_messages(tmp_path, data, expected):
    path = _write(tmp_path, data)
    with pytest.raises(SpecError) as err:
        load_spec(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(str(path))
    for fragment in expected:
        assert fragment in msg


def test_a_geometry_file_given_as_a_spec_gets_a_hint(tmp_path, neuro_geometry_file):
    with pytest.raises(SpecError) as err:
        load_spec(neuro_geometry_file)
    assert str(err.value) == (f"{neuro_geometry_file}: this is a geometry file (chic-design build writes it), not a "
                              "design spec; give a spec such as designs/neuro.yaml")


def test_not_yaml_and_missing_file(tmp_path):
    with pytest.raises(SpecError, match="no such spec file"):
        load_spec(tmp_path / "nope.yaml")
    with pytest.raises(SpecError, match=r"not valid YAML at line 3 \(expected"):
        load_spec(_write(tmp_path, "name: a\nbody: [1, 2\n"))
    with pytest.raises(SpecError, match="must be a YAML mapping"):
        load_spec(_write(tmp_path, "- 1\n- 2\n"))


def test_cli_reports_spec_errors_without_traceback(tmp_path, capsys):
    path = _write(tmp_path, _mutate(["body", "length"], 0))
    assert main(["build", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "body.length" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()  # validation happens before any CAD work


def test_schema_is_json_schema_of_the_spec(capsys):
    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema["title"] == "CHIC fiducial design spec"
    assert set(schema["required"]) == {"name", "body", "channels"}
    assert schema["$defs"]["BodySpec"]["additionalProperties"] is False


def test_schema_documents_the_physical_ranges():
    body = json_schema()["$defs"]["BodySpec"]["properties"]
    assert body["length"]["maximum"] == 200 and body["length"]["minimum"] == 2
    assert json_schema()["properties"]["name"]["maxLength"] == 64
