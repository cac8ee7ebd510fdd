"""Shared fixtures: the repository's designs and their geometry, the z001 Z-frame, a DICOM slice, an oblique volume."""

from pathlib import Path

import pytest

from chic_design.families import family_of, geometry_of
from chic_design.spec import load_spec
from chic_register.imaging.simulate import simulate_slice, simulate_volume, write_simulated
from chic_register.model.geometry import write_geometry
from tests.helpers import OBLIQUE, T_TRUE, zframe

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


ZFRAME = ROOT / "designs" / "zframe.yaml"


@pytest.fixture(scope="module")
def z001():
    """The z001 Z-frame of 3D Slicer's ZFrameRegistration as seven line tubes (tests.helpers.zframe)."""
    return zframe()


@pytest.fixture(scope="module")
def dicom_slice(tmp_path_factory, neuro_geometry):
    """A simulated neuro slice written as DICOM: (its path, its true T_scanner_from_fiducial)."""
    sim = simulate_slice(neuro_geometry, 25.0, 10.0, 30.0, 20.0, noise="rician", snr=25.0, rng=1)
    path, _ = write_simulated(sim, tmp_path_factory.mktemp("dcm") / "ok.dcm")
    return path, sim.truth.T_scanner_from_fiducial


@pytest.fixture(scope="module")
def sim_volume(neuro_geometry):
    """A noisy neuro volume acquired obliquely (tests.helpers.OBLIQUE) with the fiducial at tests.helpers.T_TRUE."""
    return simulate_volume(neuro_geometry, T_TRUE, (128, 128, 60), (0.5, 0.5, 1.0), direction=OBLIQUE,
                           origin_mm=None, noise="rician", snr=25.0, rng=3)
