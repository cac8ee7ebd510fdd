"""One volume path: ``chic-register solve VOLUME`` and the library's ``register_volume`` give the same pose."""

import json

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.imaging.simulate import simulate_volume
from chic_register.io.volumes import read_volume, write_volume
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import rigid, rot_y, rot_z
from chic_register.pipeline.volume import register_volume


@pytest.mark.slow
def test_a_wide_blob_volume_gives_the_same_pose_on_the_command_line(tmp_path, neuro_geometry, capsys):
    """Blobs twice the channels' width (no slice alone gives a pose; the volume's own path does)."""
    L = neuro_geometry.body.length
    T = rigid(rot_z(30.0) @ rot_y(10.0), (1.0, -2.0, -L / 2))
    sv = simulate_volume(neuro_geometry, T, (128, 128, 40), (0.5, 0.5, 2.0), noise="rician", snr=20, rng=1,
                         supersample=2, thickness_samples=2, blob_width=2.0)
    path = write_volume(sv.volume, tmp_path / "wide.nrrd")
    geom_file = write_geometry(neuro_geometry, tmp_path / "geometry.yaml")
    lib = register_volume(read_volume(path), neuro_geometry)
    assert main(["solve", str(path), "--geometry", str(geom_file), "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(np.array(cli["T_scanner_from_fiducial"]), lib.T_scanner_from_fiducial, atol=1e-9)
    assert [s["source"] for s in cli["slices"]] == [s.source for s in lib.slices]
    assert any("wide blobs were fitted" in s.reason for s in lib.skipped)
