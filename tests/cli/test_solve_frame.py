"""solve --frame: a CHIC and a stereotactic frame from the same DICOM slice, the CHIC in frame coordinates."""

from __future__ import annotations

import json

import numpy as np

from chic_register.cli.main import main
from chic_register.io.dicom import write_dicom
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import invert
from tests.helpers import LEKSELL_T, both_in_one_slice, three_plate_frame


def test_solve_with_a_frame_reports_the_fiducial_in_leksell_coordinates(tmp_path, capsys, neuro_geometry):
    frame = three_plate_frame()
    sl, T_frame, T_chic = both_in_one_slice(frame, neuro_geometry, 20.0, "MR")
    dcm = write_dicom(sl, tmp_path / "both.dcm")
    g_chic = write_geometry(neuro_geometry, tmp_path / "neuro.yaml")
    g_frame = write_geometry(frame, tmp_path / "frame.yaml")
    rc = main(["solve", str(dcm), "--geometry", str(g_chic), "--frame", str(g_frame), "--frame-prior", "LPS",
               "--target", "0", "0", "-60", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["status"] == "ok" and doc["frame"]["status"] == "ok"
    rel = doc["frame"]["fiducial_in_frame"]
    truth = LEKSELL_T @ invert(T_frame) @ T_chic @ np.array([0.0, 0.0, -60.0, 1.0])
    err = np.linalg.norm(np.array(rel["target_frame_mm"]) - truth[:3])
    assert rel["frame"] == "leksell" and rel["target_F_mm"] == [0.0, 0.0, -60.0]
    assert err < 0.5 and err < 5 * rel["predicted_tre_mm"] + 0.05  # 60 mm below the body: rotation errors grow
    assert rel["predicted_tre_mm"] > 0


def test_a_missing_frame_file_is_one_line(tmp_path, capsys, neuro_geometry):
    frame = three_plate_frame()
    sl, _, _ = both_in_one_slice(frame, neuro_geometry, 20.0, "MR")
    dcm = write_dicom(sl, tmp_path / "both.dcm")
    g_chic = write_geometry(neuro_geometry, tmp_path / "neuro.yaml")
    rc = main(["solve", str(dcm), "--geometry", str(g_chic), "--frame", str(tmp_path / "nope.yaml")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "nope.yaml" in err
    assert_one_line_text(err)


def assert_one_line_text(err: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
