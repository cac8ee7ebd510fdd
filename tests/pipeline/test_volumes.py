"""Volumes registered: a Z-frame volume without slice indices (empty and disagreeing slices reported), slice index
ranges, the same pose from every file format, a neuro volume, and the command line's volume solve.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.errors import ChicRegisterError
from chic_register.imaging.simulate import simulate_volume
from chic_register.io.volumes import read_volume, write_volume
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import apply, rigid, rot_y, rot_z
from chic_register.pipeline.register import register
from chic_register.pipeline.volume import parse_slice_indices, register_volume
from tests.helpers import T_TRUE, ZF_CENTRE, pose_difference, tre_mm


@pytest.fixture(scope="module")
def zf_volume(z001):
    """A tilted Z-frame in a volume reaching 8-10 mm past both ends of the frame (empty slices there)."""
    T = rigid(rot_z(20) @ rot_y(8), (2.0, -3.0, -30.0))
    sv = simulate_volume(z001, T, (112, 112, 52), (1.0, 1.0, 1.5), noise="rician", snr=20, rng=5, supersample=2,
                         thickness_samples=2)
    return sv


def test_zframe_volume_registers_without_slices(z001, zf_volume):
    T = zf_volume.T_scanner_from_fiducial
    reg = register_volume(zf_volume.volume, z001, prior=rigid(T[:3, :3] @ rot_z(-30), (0, 0, 0)))
    assert tre_mm(reg.T_scanner_from_fiducial, T, ZF_CENTRE) < 0.3
    used = {s.source for s in reg.slices}
    skipped = {s.source: s.reason for s in reg.skipped}
    assert len(used) >= 25 and len(used) + len(skipped) == 52 and not used & set(skipped)
    assert skipped["<simulated>[k=0]"].startswith("the slice misses the frame")
    d = reg.to_dict()
    assert d["n_slices_used"] == len(used) and len(d["skipped_slices"]) == len(skipped)


def test_a_slice_disagreeing_with_the_volume_is_reported(z001, zf_volume):
    """One slice's pixels swapped for another's: it locks alone but not with the rest; named with its residual."""
    v = zf_volume.volume
    vox = np.array(v.voxels)
    vox[26] = np.roll(vox[26], 3, axis=1)  # 2.7 mm off along i
    bad = dataclasses.replace(v, voxels=vox)
    T = zf_volume.T_scanner_from_fiducial
    reg = register_volume(bad, z001, indices=None, prior=rigid(T[:3, :3], (0, 0, 0)))
    assert tre_mm(reg.T_scanner_from_fiducial, T, ZF_CENTRE) < 0.3
    off = [s for s in reg.skipped if s.source.endswith("[k=26]")]
    assert off and "disagrees with the other slices" in off[0].reason and off[0].residual_rms_mm > 0.5


def test_cli_solves_a_volume_without_slices_and_with_ranges(tmp_path, z001, zf_volume, capsys):
    geo = write_geometry(z001, tmp_path / "zframe.yaml")
    vol = write_volume(zf_volume.volume, tmp_path / "z001.nii.gz")
    prior = tmp_path / "prior.json"
    prior.write_text(json.dumps({"T_scanner_from_fiducial": zf_volume.T_scanner_from_fiducial.tolist()}))
    base = ["solve", str(vol), "--geometry", str(geo), "--prior", str(prior), "--json"]
    assert main(base) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_slices_used"] >= 25 and out["skipped_slices"][0]["source"].endswith("[k=0]")
    assert tre_mm(np.array(out["T_scanner_from_fiducial"]), zf_volume.T_scanner_from_fiducial, ZF_CENTRE) < 0.3
    assert main(base + ["--slices", "20-23", "30"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["source"][-6:] for s in out["slices"]] == ["[k=20]", "[k=21]", "[k=22]", "[k=23]", "[k=30]"]
    assert main(base[:-3] + ["--json"]) == 3  # no prior: the self-symmetric frame is refused
    assert "ambiguous fit" in json.loads(capsys.readouterr().out)["reason"]


def test_slice_index_ranges():
    assert parse_slice_indices(["5-7", "2", "6", "-1"], 10) == [5, 6, 7, 2, 9]
    for bad, msg in (("7-5", "low to high"), ("a", "not a slice index"), ("3-12", "outside 0..9")):
        with pytest.raises(ChicRegisterError, match=msg):
            parse_slice_indices([bad], 10)


def test_same_pose_from_nifti_nrrd_and_dicom(tmp_path, neuro_geometry, sim_volume):

    poses = {}
    for name in ("vol.nii.gz", "vol.nrrd", "series"):
        v = read_volume(write_volume(sim_volume.volume, tmp_path / name))
        reg = register([v.native_slice(k) for k in (22, 30, 38)], neuro_geometry)
        poses[name] = reg.T_scanner_from_fiducial
    ref = poses["vol.nii.gz"]
    for name, T in poses.items():
        d_mm, ang = pose_difference(ref, T)
        assert d_mm < 0.05 and ang < 0.05, (name, d_mm, ang)
    d_mm, ang = pose_difference(ref, T_TRUE)
    assert d_mm < 0.5 and ang < 0.5, (d_mm, ang)


def test_cli_solve_volume_slices_jointly(tmp_path, neuro_geometry_file, sim_volume, capsys):
    import json

    from chic_register.cli.main import main

    path = write_volume(sim_volume.volume, tmp_path / "vol.nii.gz")
    rc = main(["solve", str(path), "--slices", "22", "30", "38", "--geometry", str(neuro_geometry_file), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and len(out["slices"]) == 3
    assert out["slices"][1]["source"].endswith("[k=30]")
    d_mm, ang = pose_difference(np.array(out["T_scanner_from_fiducial"]), T_TRUE)
    assert d_mm < 0.5 and ang < 0.5
    assert main(["solve", str(path), "--slices", "99", "--geometry", str(neuro_geometry_file)]) == 2
    assert "slice index 99 is outside 0..59" in capsys.readouterr().err


@pytest.mark.slow
def test_neuro_volume_registers_without_slices_leaving_out_the_slices_that_fail_verification(neuro_geometry):
    """A 60-slice neuro volume reaching past both end faces registers jointly from the slices that hold the body;
    each slice left out says why (those past the ends: the slice misses the frame)."""
    from chic_register.pipeline.volume import register_volume

    T = rigid(rot_z(20) @ rot_y(8), (1.0, -1.0, -25.0))
    sv = simulate_volume(neuro_geometry, T, (128, 128, 60), (0.5, 0.5, 1.0), noise="rician", snr=20, rng=1,
                         supersample=2, thickness_samples=2)
    reg = register_volume(sv.volume, neuro_geometry)
    centre = np.array([0.0, 0.0, neuro_geometry.body.length / 2])
    assert np.linalg.norm(apply(reg.T_scanner_from_fiducial, centre) - apply(T, centre)) < 0.05
    assert len(reg.slices) >= 40
    used = {s.source for s in reg.slices}
    assert all(s.reason and s.source not in used for s in reg.skipped)
    assert any(s.reason.startswith("the slice misses the frame") for s in reg.skipped)
