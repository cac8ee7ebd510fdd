"""Helpers shared by tests in several folders: the hunts' geometries and cases, slices and their errors."""

from __future__ import annotations

import functools

from chic_design.layout import fiducial_geometry
from chic_design.spec import load_spec
from chic_register.model.geometry import load_geometry
from chic_register.studies.damage import make_case, run_case
from tests.conftest import ROOT

#: The false-lock hunts' designs (``benchmarks/hunt.py``'s default geometries).
HUNT_DESIGNS = {"neuro": ROOT / "designs" / "neuro.yaml", "needle-guide": ROOT / "designs" / "needle-guide.yaml"}


@functools.lru_cache(maxsize=1)
def hunt_geometries() -> dict:
    """The geometries the hunts solve with, by name: the exports, or the same built from ``designs/``."""
    out = {}
    for name, spec in HUNT_DESIGNS.items():
        export = ROOT / "exports" / name / "geometry.yaml"
        out[name] = load_geometry(export) if export.exists() else fiducial_geometry(load_spec(spec))
    return out


def run_hunt_case(index: int, seed: int = 0) -> dict:
    """The hunt's judged outcome of one of its cases (``benchmarks/hunt.py --seed SEED --case INDEX``)."""
    geoms = hunt_geometries()
    return run_case(make_case(index, seed, geoms), geoms)
