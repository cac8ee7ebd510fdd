"""track over OpenIGTLink: a scanner bridge (pyigtl IMAGE messages) in, TRANSFORM + STATUS back on the same link."""

from __future__ import annotations

import json
import math
import socket
import threading
import time

import numpy as np
import pytest

from chic_register.imaging.simulate import simulate_slice
from chic_register.io.igtl import IgtlServer, read_message, slice_to_image_message
from chic_register.io.transforms import ras_matrix
from chic_register.live.igtl_track import track_images
from chic_register.model.pose import apply

# tilted slices: a near-normal single slice knows its tilt only to ~0.3 deg, which the solver's default trust
# limits (0.5 deg at 3 sigma, chic_register.verify.pixels) refuse
POSES = [(20.0, 35.0, 30.0, 20.0), (25.0, 40.0, -60.0, 100.0), (30.0, 35.0, 150.0, -40.0)]


def _distance_mm(T1, T2) -> float:
    pts = np.array([[15.0, 0, 0], [0, 15.0, 50.0], [-15.0, 0, 25.0], [0, 0, 0], [0, 0, 50.0]])
    return float(np.linalg.norm(apply(T1, pts) - apply(T2, pts), axis=1).max())


@pytest.fixture(scope="module")
def stream(neuro_geometry):
    """Three simulated 256x256 slices, as the scanner would send them (tilts that lock robustly under the
    solver's verification: near-normal slices can be refused as imprecise)."""
    sims = [simulate_slice(neuro_geometry, *a, noise="rician", snr=40.0, rng=n,
                           image_position=(-60.0 + n, -70.0, 5.0 * n)) for n, a in enumerate(POSES)]
    return sims


class Bridge:
    """The scanner bridge: a TCP server that sends IMAGE messages and collects what comes back."""

    def __init__(self):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]

    def serve(self, images, replies_per_image):
        conn, _ = self.listener.accept()
        out = []
        with conn:
            for img in images:
                conn.sendall(img.pack())
                got = []
                while not any(m.message_type == "STATUS" for m in got):  # STATUS ends each reply
                    got.append(read_message(conn, timeout_s=20.0))
                out.append(got)
        self.listener.close()
        return out


def test_image_stream_in_poses_and_status_out(stream, neuro_geometry):
    bridge = Bridge()
    images = [slice_to_image_message(s.slice, "MRI", timestamp=1000.0 + k) for k, s in enumerate(stream)]
    blank = slice_to_image_message(stream[0].slice, "MRI", timestamp=2000.0)
    blank.image = np.zeros_like(blank.image)
    result = {}
    th = threading.Thread(target=lambda: result.update(replies=bridge.serve(images + [blank], 6)), daemon=True)
    th.start()
    events = []
    summary = track_images(neuro_geometry, connect=f"127.0.0.1:{bridge.port}", max_images=4, timeout_s=60.0,
                           on_event=events.append)
    th.join(30)
    replies = result["replies"]
    assert summary.stopped_by == "max_files" and [e.status for e in events] == ["ok", "ok", "ok", "no_lock"]
    for k, (sim, got) in enumerate(zip(stream, replies)):
        kinds = [(m.message_type, m.device_name) for m in got]
        assert kinds == [("TRANSFORM", "CHIC"), ("TRANSFORM", "CHICToRAS"), ("STRING", "CHICQuality"),
                         ("STATUS", "CHIC")]
        assert got[-1].code == 1
        assert all(m.timestamp == pytest.approx(1000.0 + k, abs=1e-6) for m in got)  # pairs reply with image
        T = np.linalg.inv(ras_matrix(np.eye(4))) @ got[1].matrix  # back to LPS
        assert _distance_mm(T, sim.truth.T_scanner_from_fiducial) < 0.5
        assert json.loads(got[2].string)["residual_rms_mm"] < 0.2
        assert events[k].latency_ms >= events[k].solve_ms > 0
    last = replies[3]
    assert [(m.message_type, m.device_name) for m in last] == [("STRING", "CHICQuality"), ("STATUS", "CHIC")]
    assert last[1].code == 4 and last[1].error_name == "no_lock" and last[1].status_string == events[3].reason
    assert math.isfinite(summary.to_dict()["latency_ms"]["median"])


def test_listen_mode_waits_for_the_bridge_and_survives_a_reconnect(stream, neuro_geometry):
    with IgtlServer(0, host="127.0.0.1") as srv:
        got = []

        def bridge():
            for k in range(2):  # connects, sends one image, reads the reply, hangs up; twice
                with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as conn:
                    conn.sendall(slice_to_image_message(stream[k].slice, "MRI").pack())
                    while not got or got[-1].message_type != "STATUS" or len(got) < 4 * (k + 1):
                        got.append(read_message(conn, timeout_s=20.0))

        th = threading.Thread(target=bridge, daemon=True)
        th.start()
        summary = track_images(neuro_geometry, listen=srv, max_images=2, timeout_s=60.0)
        th.join(30)
    assert [e.status for e in summary.events] == ["ok", "ok"]
    assert [m.device_name for m in got if m.message_type == "TRANSFORM"] == ["CHIC", "CHICToRAS"] * 2


def test_cli_track_igtl_images(stream, neuro_geometry_file, capsys, tmp_path):
    from chic_register.cli.main import main

    bridge = Bridge()
    th = threading.Thread(target=bridge.serve, args=([slice_to_image_message(stream[1].slice, "MRI")], 6),
                          daemon=True)
    th.start()
    rc = main(["track", "-", "--geometry", str(neuro_geometry_file), "--igtl-images", f"127.0.0.1:{bridge.port}",
               "--max-files", "1", "--timeout", "60", "--json", "--scene", str(tmp_path / "scenes")])
    th.join(30)
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert rc == 0 and lines[0]["status"] == "ok" and lines[0]["source"] == "igtl:MRI#1"
    assert _distance_mm(np.array(lines[0]["T_scanner_from_fiducial"]), stream[1].truth.T_scanner_from_fiducial) < 0.5
    assert lines[-1]["stopped_by"] == "max_files" and lines[-1]["outputs_failed"] == 0
    assert (tmp_path / "scenes" / "image_00001" / "scene.mrml").is_file()
    assert main(["track", "somewhere", "--geometry", str(neuro_geometry_file), "--igtl-images", "h:1"]) == 2
    assert "give '-'" in capsys.readouterr().err


def test_a_bad_image_is_answered_with_status_and_tracking_goes_on(stream, neuro_geometry):
    import pyigtl

    bridge = Bridge()
    tiny = pyigtl.ImageMessage(np.zeros((1, 4, 4), dtype=np.int16), device_name="MRI")  # 4x4: not a slice
    good = slice_to_image_message(stream[0].slice, "MRI")
    result = {}
    th = threading.Thread(target=lambda: result.update(replies=bridge.serve([tiny, good], 6)), daemon=True)
    th.start()
    summary = track_images(neuro_geometry, connect=f"127.0.0.1:{bridge.port}", max_images=2, timeout_s=60.0)
    th.join(30)
    bad, ok = result["replies"]
    assert bad[-1].code == 4 and bad[-1].status_string.startswith("bad IMAGE:") and "8x8" in bad[-1].status_string
    assert ok[-1].code == 1 and [e.status for e in summary.events] == ["no_lock", "ok"]


def test_pyigtl_server_as_the_scanner_bridge(stream, neuro_geometry):
    """pyigtl's own server (its threads, its parser) plays the scanner: IMAGE out, our TRANSFORM and STRING back."""
    import signal

    import pyigtl

    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    try:
        th = threading.Thread(target=lambda: track_images(neuro_geometry, connect=f"127.0.0.1:{port}", max_images=1,
                                                          timeout_s=60.0), daemon=True)
        th.start()
        end = time.monotonic() + 20
        while not server.is_connected() and time.monotonic() < end:
            time.sleep(0.02)
        server.send_message(slice_to_image_message(stream[2].slice, "MRI"))
        msg = server.wait_for_message("CHICToRAS", timeout=30.0)
        quality = server.wait_for_message("CHICQuality", timeout=5.0)
        th.join(30)
    finally:
        server.stop()
        for sig, handler in saved.items():
            signal.signal(sig, handler)
    assert msg is not None and quality is not None
    T = np.diag([-1.0, -1.0, 1.0, 1.0]) @ msg.matrix
    assert _distance_mm(T, stream[2].truth.T_scanner_from_fiducial) < 0.5
    assert json.loads(quality.string)["status"] == "ok"
