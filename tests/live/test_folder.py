"""Live tracking: slices dropped into a watched folder are registered one by one, partial files retried."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.live.folder import track
from chic_register.model.pose import apply
from tests.helpers import edited_dicom

# near-normal slices: their tilt is known to ~0.3 deg, more than the solver's default trust limit proves; these
# tests are about tracking files, so they lift the precision refusal (every other check of the pose applies)
LOW_TILT = {"trust_tre_mm": math.inf, "trust_rot_deg": math.inf}
POSES = [(18.0, 10.0, 30.0, 20.0), (25.0, 5.0, -60.0, 100.0), (32.0, 12.0, 150.0, -40.0)]


def _pose_difference(T1, T2):
    pts = np.array([[15.0, 0, 0], [0, 15.0, 50.0], [-15.0, 0, 25.0], [0, 0, 0], [0, 0, 50.0]])
    d = np.linalg.norm(apply(T1, pts) - apply(T2, pts), axis=1).max()
    dR = T1[:3, :3].T @ T2[:3, :3]
    return float(d), math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))


@pytest.fixture(scope="module")
def staged(tmp_path_factory, neuro_geometry):
    """Three simulated DICOM slices (outside the watched folder) and their true poses."""
    stage = tmp_path_factory.mktemp("stage")
    out = []
    for n, angles in enumerate(POSES):
        sim = simulate_slice(neuro_geometry, *angles, noise="rician", snr=25.0, rng=n,
                             image_position=(-60.0 + n, -70.0, 10.0 * n))
        path, _ = write_simulated(sim, stage / f"img{n:03d}.dcm")
        out.append((path, sim.truth.T_scanner_from_fiducial))
    return out


class _Runner:
    """track() in a thread; collects events and messages."""

    def __init__(self, folder, geom, **kwargs):
        self.events, self.messages, self.summary, self.error = [], [], None, None

        def run():
            try:
                self.summary = track(folder, geom, on_event=self.events.append,
                                     on_message=self.messages.append, **kwargs)
            except BaseException as exc:  # surfaced by join()
                self.error = exc

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        time.sleep(0.3)  # let it take its first snapshot of the folder

    def join(self, timeout=60.0):
        self.thread.join(timeout)
        assert not self.thread.is_alive(), "track did not stop"
        if self.error:
            raise self.error
        return self.summary


def test_registers_files_one_by_one_including_a_slow_one(tmp_path, neuro_geometry, staged):
    watch = tmp_path / "incoming"
    watch.mkdir()
    (watch / "old.dcm").write_bytes(staged[0][0].read_bytes())  # present before the start: skipped
    runner = _Runner(watch, neuro_geometry, max_files=3, timeout_s=45.0, poll_s=0.02, settle_s=0.15,
                     **LOW_TILT)
    shutil.copy(staged[0][0], watch / "a.dcm")
    time.sleep(0.5)
    shutil.copy(staged[1][0], watch / "b.dcm")
    time.sleep(0.5)
    data = staged[2][0].read_bytes()
    with open(watch / "c.dcm", "wb") as fh:  # written slowly, in two pieces
        fh.write(data[: len(data) // 2])
        fh.flush()
        time.sleep(1.0)  # long enough for a read attempt on the half file
        fh.write(data[len(data) // 2 :])
    summary = runner.join()

    assert summary.stopped_by == "max_files"
    assert [e.source.rsplit("/", 1)[-1] for e in runner.events] == ["a.dcm", "b.dcm", "c.dcm"]
    for event, (_, T_true) in zip(runner.events, staged):
        assert event.status == "ok", event.reason
        d_mm, ang = _pose_difference(event.T_scanner_from_fiducial, T_true)
        assert d_mm < 0.5 and ang < 0.5, (event.source, d_mm, ang)
        assert event.latency_ms >= event.solve_ms > 0
    assert any("c.dcm" in m and "will retry" in m for m in runner.messages), runner.messages
    assert runner.events[2].latency_ms > 1000.0  # counted from the first half's appearance
    assert summary.pending == ()


def test_unreadable_file_is_reported_once_and_kept_pending(tmp_path, neuro_geometry, staged):
    runner = _Runner(tmp_path, neuro_geometry, max_files=1, timeout_s=20.0, poll_s=0.02, settle_s=0.1,
                     **LOW_TILT)
    (tmp_path / "junk.dcm").write_bytes(b"\0" * 128 + b"DICM" + b"garbage" * 10)
    (tmp_path / ".hidden.dcm").write_bytes(b"x")
    (tmp_path / "notes.json").write_text("{}")
    time.sleep(1.5)
    shutil.copy(staged[1][0], tmp_path / "good.dcm")
    summary = runner.join()
    assert [e.status for e in runner.events] == ["ok"]
    assert len([m for m in runner.messages if "junk.dcm" in m]) == 1, runner.messages
    assert not any("hidden" in m or "notes" in m for m in runner.messages)
    assert [p.rsplit("/", 1)[-1] for p in summary.pending] == ["junk.dcm"]


def test_existing_files_and_no_lock(tmp_path, neuro_geometry, staged):

    shutil.copy(staged[0][0], tmp_path / "a.dcm")
    hour_ago = time.time() - 3600.0
    os.utime(tmp_path / "a.dcm", (hour_ago, hour_ago))  # written long before tracking started
    np.save(tmp_path / "blank.npy", np.zeros((64, 64)))
    summary = track(tmp_path, neuro_geometry, include_existing=True, pixel_spacing=(0.5, 0.5), max_files=2,
                    timeout_s=20.0, poll_s=0.02, settle_s=0.0, on_event=lambda e: None, on_message=lambda m: None)
    by_name = {e.source.rsplit("/", 1)[-1]: e for e in summary.events}
    assert by_name["a.dcm"].status == "ok"
    assert by_name["a.dcm"].latency_ms < 10_000  # from when tracking saw it, not an hour
    assert by_name["blank.npy"].status == "no_lock" and by_name["blank.npy"].reason


def test_timeout_and_ctrl_c_stop_cleanly(tmp_path, neuro_geometry, staged):
    summary = track(tmp_path, neuro_geometry, timeout_s=0.3, poll_s=0.02, on_event=None, on_message=None)
    assert summary.stopped_by == "timeout" and summary.events == ()

    def interrupted(slices, geom, **kw):
        raise KeyboardInterrupt

    shutil.copy(staged[0][0], tmp_path / "a.dcm")
    summary = track(tmp_path, neuro_geometry, include_existing=True, timeout_s=20.0, poll_s=0.02, settle_s=0.0,
                    register=interrupted, on_event=None, on_message=None)
    assert summary.stopped_by == "interrupt"
    assert "stopped (interrupt)" in summary.text()


def test_poses_are_sent_over_openigtlink(tmp_path, neuro_geometry, staged):
    pyigtl = pytest.importorskip("pyigtl")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    try:
        shutil.copy(staged[1][0], tmp_path / "b.dcm")
        summary = track(tmp_path, neuro_geometry, include_existing=True, max_files=1, timeout_s=20.0,
                        poll_s=0.02, settle_s=0.0, igtl=f"127.0.0.1:{port}", igtl_name="TRK",
                        on_event=None, on_message=None, **LOW_TILT)
        event = summary.events[0]
        assert event.igtl == "sent"
        flip = np.diag([-1.0, -1.0, 1.0, 1.0])
        msg = server.wait_for_message("TRKToRAS", timeout=5.0)  # F to RAS, for the robot
        assert msg is not None
        np.testing.assert_allclose(msg.matrix, flip @ event.T_scanner_from_fiducial, atol=1e-3)
        msg = server.wait_for_message("TRK", timeout=5.0)  # places the SPACE=LPS models in Slicer
        np.testing.assert_allclose(msg.matrix, flip @ event.T_scanner_from_fiducial @ flip, atol=1e-3)
    finally:
        server.stop()
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def test_cli_track_prints_json_lines(tmp_path, neuro_geometry_file, staged, capsys):

    from chic_register.cli.main import main

    watch = tmp_path / "w"
    watch.mkdir()
    shutil.copy(staged[2][0], watch / "c.dcm")
    rc = main(["track", str(watch), "--geometry", str(neuro_geometry_file), "--existing", "--max-files", "1",
               "--timeout", "30", "--settle", "0", "--json"])
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert rc == 0
    assert lines[0]["status"] == "ok" and lines[0]["source"].endswith("c.dcm")
    d_mm, ang = _pose_difference(np.array(lines[0]["T_scanner_from_fiducial"]), staged[2][1])
    assert d_mm < 0.5 and ang < 0.5
    assert lines[0]["latency_ms"] > 0
    assert lines[-1]["stopped_by"] == "max_files" and lines[-1]["ok"] == 1
    capsys.readouterr()
    assert main(["track", str(tmp_path / "nope"), "--geometry", str(neuro_geometry_file), "--timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert "nope: not a folder" in err and "watching" not in err
    assert main(["track", str(watch), "--geometry", str(neuro_geometry_file), "--igtl", "host:x"]) == 2


def test_cli_track_holds_an_unmeasured_scale_when_told(tmp_path, neuro_geometry_file, staged, capsys):
    """``track --scale-sd`` registers as ``solve --scale-sd`` does: 1 % of unmeasured scale is more doubt than the
    trust limits allow one slice, so the slice that locks without it is refused, naming the scale."""
    from chic_register.cli.main import main

    watch = tmp_path / "w"
    watch.mkdir()
    shutil.copy(staged[2][0], watch / "c.dcm")
    args = ["track", str(watch), "--geometry", str(neuro_geometry_file), "--existing", "--max-files", "1",
            "--timeout", "30", "--settle", "0", "--json"]
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["status"] == "ok"
    assert main([*args, "--scale-sd", "1"]) == 0
    event = json.loads(capsys.readouterr().out.splitlines()[0])
    assert event["status"] == "no_lock" and "unmeasured scale (--scale-sd)" in event["reason"]
    assert main([*args, "--scale-sd", "-1"]) == 2
    assert "--scale-sd takes a per cent in [0, 5], got -1" in capsys.readouterr().err


def test_track_folder_serves_poses_to_peers_that_connect(tmp_path, neuro_geometry):
    pytest.importorskip("pyigtl")  # as every OpenIGTLink test
    from chic_register.io.igtl import IgtlServer, read_message
    from chic_register.io.transforms import ras_matrix

    sims = [simulate_slice(neuro_geometry, 20.0 + 5 * k, 8.0, 30.0 * k, 10.0, rng=k) for k in range(2)]
    stage = tmp_path / "stage"
    stage.mkdir()
    files = [write_simulated(s, stage / f"{k}.dcm")[0] for k, s in enumerate(sims)]
    watch = tmp_path / "w"
    watch.mkdir()
    shutil.copy(files[0], watch / "0.dcm")  # registered before anybody listens: not a failure
    with IgtlServer(0, host="127.0.0.1") as srv:
        events = []

        def on_event(e):
            events.append(e)
            if len(events) == 1:  # a viewer connects after the first pose, then the second slice arrives
                viewer.append(socket.create_connection(("127.0.0.1", srv.port), timeout=5))
                time.sleep(0.1)
                shutil.copy(files[1], watch / "1.dcm")

        viewer = []
        summary = track(watch, neuro_geometry, include_existing=True, max_files=2, timeout_s=60.0, poll_s=0.02,
                        settle_s=0.0, link=srv, on_event=on_event, on_message=None)
        got = [read_message(viewer[0], timeout_s=5.0) for _ in range(4)]
        viewer[0].close()
    assert [e.igtl for e in events] == ["no peer connected", "sent"] and summary.outputs_failed == 0
    assert [m.device_name for m in got] == ["CHIC", "CHICToRAS", "CHICQuality", "CHIC"]
    np.testing.assert_allclose(got[1].matrix, ras_matrix(sims[1].truth.T_scanner_from_fiducial), atol=0.05)


def test_track_survives_a_bad_file_and_registers_the_next(tmp_path, dicom_slice, neuro_geometry):
    watch = tmp_path / "w"
    watch.mkdir()
    edited_dicom(dicom_slice[0], watch / "a_bad.dcm", PixelSpacing=["1e-300", "1e-300"])
    (watch / "b_good.dcm").write_bytes(dicom_slice[0].read_bytes())
    events, messages = [], []
    summary = track(watch, neuro_geometry, include_existing=True, max_files=1, timeout_s=60, settle_s=0.0,
                    on_event=events.append, on_message=messages.append)
    assert [Path(e.source).name for e in events] == ["b_good.dcm"] and events[0].status == "ok"
    assert summary.stopped_by == "max_files"
    assert any("a_bad.dcm" in m and "PixelSpacing" in m for m in messages)


def test_track_reports_an_unexpected_failure_and_goes_on(tmp_path, dicom_slice, neuro_geometry):
    from chic_register.pipeline.register import register

    watch = tmp_path / "w"
    watch.mkdir()
    for name in ("a.dcm", "b.dcm"):
        (watch / name).write_bytes(dicom_slice[0].read_bytes())

    def flaky(slices, geom, **kw):
        if slices[0].source.endswith("a.dcm"):
            raise ZeroDivisionError("float division by zero")
        return register(slices, geom, **kw)

    events = []
    summary = track(watch, neuro_geometry, include_existing=True, max_files=2, timeout_s=60, settle_s=0.0,
                    on_event=events.append, on_message=None, register=flaky)
    assert [(Path(e.source).name, e.status) for e in events] == [("a.dcm", "error"), ("b.dcm", "ok")]
    assert "ZeroDivisionError" in events[0].reason and "a.dcm: error: ZeroDivisionError" in events[0].text()
    assert summary.to_dict()["errors"] == 1 and summary.to_dict()["no_lock"] == 0


def test_a_long_run_keeps_its_latest_events_and_counts_every_one():
    """A tracker at 10 images a second for hours: the summary counts every image and keeps the latest
    KEPT_EVENTS in full, so its memory does not grow with each image."""
    from chic_register.live.folder import KEPT_EVENTS, EventLog, TrackEvent

    log = EventLog()
    n = 3 * KEPT_EVENTS + 7
    for k in range(n):
        ok = k % 4 != 0
        log.add(TrackEvent(f"igtl:MRI#{k + 1}", "ok" if ok else "no_lock", np.eye(4) if ok else None,
                           slices=("a record",), latency_ms=float(k)))
    summary = log.summary((), "timeout", 1.0)
    assert summary.files == n and len(summary.events) == KEPT_EVENTS
    assert summary.events[-1].source == f"igtl:MRI#{n}" and summary.events[-1].slices == ()
    d = summary.to_dict()
    assert d["ok"] + d["no_lock"] == n and d["no_lock"] == len(range(0, n, 4))
    assert d["latency_ms"]["max"] == float(n - 1)  # the oldest events count, though they are not kept
