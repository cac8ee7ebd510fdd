"""The tool frame: the spec's tool section, the geometry file's optional tool key and its hash."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from chic_design.errors import SpecError
from chic_design.families import geometry_of
from chic_design.spec import parse_spec
from chic_register.model.geometry import content_sha256, geometry_from_dict, load_geometry, write_geometry
from chic_register.model.pose import rigid, rot_y

from .conftest import NEURO
from .conftest import TOOL_TIP_MM as TIP_MM


def test_geometry_without_tool_keeps_its_hash_and_with_tool_covers_it(neuro_geometry, tool_geometry, tmp_path):
    plain = neuro_geometry.to_dict()
    assert "tool" not in plain  # files without the key keep the content and hash of a design without a tool
    with_tool = tool_geometry.to_dict()
    assert {k: v for k, v in with_tool.items() if k not in ("tool", "sha256")} == \
        {k: v for k, v in plain.items() if k != "sha256"}
    assert with_tool["tool"]["T_fiducial_from_tool"][2][3] == TIP_MM
    path = write_geometry(tool_geometry, tmp_path / "geometry.yaml")
    back = load_geometry(path)
    np.testing.assert_allclose(back.tool.tip_mm, [0.0, 0.0, TIP_MM])
    data = yaml.safe_load(path.read_text())
    data["tool"]["T_fiducial_from_tool"][2][3] = -50.0  # an edited tool is caught by the hash
    with pytest.raises(Exception, match="sha256 does not match"):
        geometry_from_dict(data, path)
    data["tool"]["T_fiducial_from_tool"][0][0] = 2.0
    data["sha256"] = content_sha256(data)
    with pytest.raises(Exception, match="rigid 4x4"):
        geometry_from_dict(data, path)


@pytest.mark.parametrize("tool, message", [
    ({}, "exactly one"),
    ({"tip_offset_mm": -60, "T_fiducial_from_tool": np.eye(4).tolist()}, "exactly one"),
    ({"T_fiducial_from_tool": (2 * np.eye(4)).tolist()}, "rigid 4x4"),
    ({"tip_offset_mm": -60, "colour": "red"}, "colour"),
])
def test_spec_tool_section_is_validated(tool, message):
    data = yaml.safe_load(NEURO.read_text())
    data["tool"] = tool
    with pytest.raises(SpecError, match=message):
        parse_spec(data, "neuro.yaml")


def test_full_tool_transform_from_the_spec(neuro_spec):
    T = rigid(rot_y(90.0), (1.0, 2.0, -40.0))
    data = yaml.safe_load(NEURO.read_text())
    data["tool"] = {"T_fiducial_from_tool": T.tolist()}
    geom = geometry_of(parse_spec(data, "neuro.yaml"))
    np.testing.assert_allclose(geom.tool.T_fiducial_from_tool, T)
