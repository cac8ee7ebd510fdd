"""Shared fixtures: the repository's designs and their geometry."""

from pathlib import Path

import pytest

from chic_design.families import family_of
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
