"""chic-register track on the command line: one line per image, and a "wrote" line per scene it writes."""

from __future__ import annotations

import json

from chic_register.cli.main import main
from chic_register.imaging.simulate import simulate_slice, write_simulated


def test_track_reports_each_scene_it_writes(tmp_path, neuro_geometry, neuro_geometry_file, capsys):
    watch = tmp_path / "w"
    watch.mkdir()
    sim = simulate_slice(neuro_geometry, 25.0, 10.0, 30.0, 20.0, noise="rician", snr=25.0, rng=1)
    write_simulated(sim, tmp_path / "c.dcm")
    (tmp_path / "c.dcm").rename(watch / "c.dcm")
    scenes = tmp_path / "scenes"
    rc = main(["track", str(watch), "--geometry", str(neuro_geometry_file), "--existing", "--max-files", "1",
               "--timeout", "30", "--settle", "0", "--json", "--scene", str(scenes)])
    out, err = capsys.readouterr()
    assert rc == 0
    events = [json.loads(line) for line in out.splitlines()]  # stdout: JSON lines only
    assert events[0]["status"] == "ok" and events[-1]["ok"] == 1
    mrml = scenes / "c.dcm" / "scene.mrml"
    assert mrml.is_file() and f"chic-register: wrote {mrml}" in err
