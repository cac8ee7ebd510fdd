"""A volume of the Leksell MR box: the whole volume and parts of it register and agree within their uncertainty;
one slice alone is refused (two plates facing one way: the turn about F's x is fixed only by several slices)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from chic_design.families import family_named
from chic_design.spec import load_spec
from chic_register.cli.main import main
from chic_register.model.geometry import write_geometry
from tests.helpers import ROOT


@pytest.fixture(scope="module")
def box_volume(tmp_path_factory):
    work = tmp_path_factory.mktemp("lk-volume")
    geom = write_geometry(family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / "leksell-g-mr.yaml")),
                          work / "geometry.yaml")
    vol = work / "box.nrrd"
    assert main(["simulate", "--geometry", str(geom), "--depth", "60", "--tilt", "3", "--azimuth", "30", "--twist",
                 "2", "--volume-shape", "224", "224", "24", "--voxel-size", "1", "1", "2", "--blob-width", "1.5",
                 "--noise", "rician", "--snr", "20", "--seed", "1", "--out", str(vol)]) == 0
    truth = np.array(json.loads((work / "box.nrrd.truth.json").read_text())["T_scanner_from_fiducial"])
    return geom, vol, truth


def _solve(capsys, geom, vol, *extra):
    rc = main(["solve", str(vol), "--geometry", str(geom), "--prior", "LPS", "--json", *extra])
    return rc, json.loads(capsys.readouterr().out)


def _error(doc, truth):
    T = np.array(doc["T_scanner_from_fiducial"])
    p = np.array([0.0, 0.0, 60.0, 1.0])
    return float(np.linalg.norm((T @ p - truth @ p)[:3])), T


def test_the_whole_volume_and_its_halves_agree_within_their_uncertainty(capsys, box_volume):
    geom, vol, truth = box_volume
    rc, doc = _solve(capsys, geom, vol)
    assert rc == 0 and doc["n_slices_used"] == 24
    err, _ = _error(doc, truth)
    assert err < 0.3
    halves = []
    for part in ("0-11", "12-23"):
        rc, doc = _solve(capsys, geom, vol, "--slices", part)
        assert rc == 0, doc
        halves.append((_error(doc, truth)[1], doc["predicted_tre_mm"]))
    (Ta, ta), (Tb, tb) = halves
    p = np.array([0.0, 0.0, 60.0, 1.0])
    apart = float(np.linalg.norm((Ta @ p - Tb @ p)[:3]))
    assert apart < 3 * np.hypot(ta, tb) + 0.01  # independent halves: their difference within their uncertainty
    turn = np.degrees(Rotation.from_matrix(Ta[:3, :3] @ Tb[:3, :3].T).magnitude())
    assert turn < 0.3


def test_one_slice_of_it_is_refused_as_imprecise(capsys, box_volume):
    geom, vol, _ = box_volume
    rc = main(["solve", str(vol), "--geometry", str(geom), "--prior", "LPS", "--slices", "12"])
    assert rc == 3
    assert "about F's x axis" in capsys.readouterr().err
