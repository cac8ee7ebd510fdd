"""Shared fixtures: the repository's designs and their geometry."""

from pathlib import Path

import pytest

from chic_design.families import family_of, geometry_of
from chic_design.spec import load_spec
from chic_register.model.geometry import write_geometry

ROOT = Path(__file__).resolve().parents[1]
NEURO = ROOT / "designs" / "neuro.yaml"
NEEDLE = ROOT / "designs" / "needle-guide.yaml"
ZFRAME = ROOT / "designs" / "zframe.yaml"


@pytest.fixture(scope="session")
def neuro_spec():
    return load_spec(NEURO)


@pytest.fixture(scope="session")
def neuro_geometry(neuro_spec):
    return family_of(neuro_spec).geometry(neuro_spec, source={"spec": "designs/neuro.yaml"})


@pytest.fixture(scope="session")
def needle_geometry():
    spec = load_spec(NEEDLE)
    return family_of(spec).geometry(spec, source={"spec": "designs/needle-guide.yaml"})


@pytest.fixture()
def neuro_geometry_file(tmp_path, neuro_geometry):
    return write_geometry(neuro_geometry, tmp_path / "geometry.yaml")


#: the tip of the tool added to the neuro design for the tool-frame and scene tests: on the axis, 60 mm below F
TOOL_TIP_MM = -60.0


@pytest.fixture(scope="session")
def tool_geometry(neuro_spec):
    """The neuro design with a tool whose tip is on the axis at z = TOOL_TIP_MM."""
    from chic_design.families.sections import ToolSpec

    spec = neuro_spec.model_copy(update={"tool": ToolSpec(tip_offset_mm=TOOL_TIP_MM)})
    return geometry_of(spec, source={"spec": "designs/neuro.yaml"})


REAL = ROOT / "tests" / "data" / "real"  # real scanner images (README there: sources and licences)


@pytest.fixture(scope="session")
def zframe_geometry():
    """The 60 mm seven-rod Z-frame of ``designs/zframe.yaml`` (ZFrameRegistration's configuration z001)."""
    return geometry_of(load_spec(ROOT / "designs" / "zframe.yaml"), source={"spec": "designs/zframe.yaml"})


@pytest.fixture()
def zframe_geometry_file(tmp_path, zframe_geometry):
    return write_geometry(zframe_geometry, tmp_path / "zframe-geometry.yaml")
