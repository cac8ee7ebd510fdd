"""OpenIGTLink both ways, on loopback: poses, quality and STATUS out (client and server); IMAGEs in."""

from __future__ import annotations

import json
import signal
import socket
import threading
import time

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from chic_register.errors import ChicRegisterError  # noqa: E402
from chic_register.io.igtl import (  # noqa: E402
    IgtlClient,
    IgtlError,
    IgtlServer,
    StatusMessage,
    check_name,
    image_to_slices,
    no_lock_messages,
    parse_address,
    pose_messages,
    read_message,
    send_pose,
    slice_to_image_message,
)
from chic_register.io.transforms import ras_matrix, slicer_matrix  # noqa: E402
from chic_register.model.pose import rigid, rot_y, rot_z  # noqa: E402

FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server():
    """A pyigtl server on 127.0.0.1 (it installs SIGINT/SIGTERM handlers: restore them after)."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    srv = pyigtl.OpenIGTLinkServer(port=_free_port(), local_server=True)
    try:
        yield srv
    finally:
        srv.stop()
        for sig, handler in saved.items():
            signal.signal(sig, handler)


class _Peer:
    """A raw TCP server on loopback that collects every OpenIGTLink message it is sent (STATUS included)."""

    def __init__(self):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.messages = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        conn, _ = self.listener.accept()
        with conn:
            while True:
                msg = read_message(conn, timeout_s=10.0)
                if msg is None:
                    return
                self.messages.append(msg)

    def wait(self, n, timeout=10.0):
        end = time.monotonic() + timeout
        while len(self.messages) < n and time.monotonic() < end:
            time.sleep(0.01)
        return self.messages

    def close(self):
        self.listener.close()


def _pose():
    return rigid(rot_z(30.0) @ rot_y(20.0) @ rot_z(-45.0), (12.5, -40.0, 7.25))


def test_frame_matrices_by_hand():
    T = _pose()
    np.testing.assert_allclose(ras_matrix(T)[:2], -T[:2])
    np.testing.assert_allclose(ras_matrix(T)[2:], T[2:])
    S = slicer_matrix(T)
    # conjugation flips the signs of the off-diagonal blocks between (x, y) and z
    np.testing.assert_allclose(S[:2, :2], T[:2, :2])
    np.testing.assert_allclose(S[:2, 2:], -T[:2, 2:])
    np.testing.assert_allclose(S[2, :2], -T[2, :2])
    np.testing.assert_allclose(S[:3, 3], [-12.5, 40.0, 7.25])  # F origin: LPS (x, y, z) is RAS (-x, -y, z)


def test_status_message_bytes_by_hand():
    msg = StatusMessage(4, "no_lock", "too few tubes", device_name="CHIC", timestamp=0.0)
    data = msg.pack()
    head = pyigtl.MessageBase.parse_header(data[:58])
    assert (head["message_type"], head["device_name"], head["body_size"]) == ("STATUS", "CHIC", 30 + 14)
    assert data[58:60] == b"\x00\x04" and data[60:68] == bytes(8)
    assert data[68:88] == b"no_lock".ljust(20, b"\0") and data[88:] == b"too few tubes\0"
    a, b = socket.socketpair()
    with a, b:
        a.sendall(data)
        back = read_message(b, timeout_s=1.0)
    assert (back.code, back.error_name, back.status_string) == (4, "no_lock", "too few tubes")


def test_pyigtl_server_receives_both_transforms_and_the_quality(server):
    T, T_tool = _pose(), _pose() @ rigid(np.eye(3), (0, 0, -60.0))
    send_pose(T, server.host, server.port, name="CHICTEST", timeout_s=2.0, T_scanner_from_tool=T_tool,
              quality={"residual_rms_mm": 0.0123, "predicted_tre_mm": 0.2})
    expect = {"CHICTEST": FLIP @ T @ FLIP, "CHICTESTToRAS": FLIP @ T,
              "CHICTESTTool": FLIP @ T_tool @ FLIP, "CHICTESTToolToRAS": FLIP @ T_tool}
    for name, M in expect.items():
        msg = server.wait_for_message(name, timeout=5.0)
        assert msg is not None and msg.message_type == "TRANSFORM", name
        np.testing.assert_allclose(msg.matrix, M, atol=1e-4)  # float32 on the wire
    q = server.wait_for_message("CHICTESTQuality", timeout=5.0)
    assert json.loads(q.string) == {"status": "ok", "residual_rms_mm": 0.0123, "predicted_tre_mm": 0.2}


def test_status_ok_and_no_lock_reach_the_peer():
    peer = _Peer()
    try:
        with IgtlClient(f"127.0.0.1:{peer.port}") as client:
            client.send(pose_messages(_pose(), "CHIC", quality={"residual_rms_mm": 0.01}))
            client.send(no_lock_messages("only 4 tubes matched", "CHIC"))
        msgs = peer.wait(6)
    finally:
        peer.close()
    status = [m for m in msgs if m.message_type == "STATUS"]
    assert [(m.code, m.error_name) for m in status] == [(1, "ok"), (4, "no_lock")]
    assert status[1].status_string == "only 4 tubes matched" and "residual_rms_mm 0.01" in status[0].status_string


def test_server_mode_sends_to_every_peer_and_reports_none():
    with IgtlServer(0, host="127.0.0.1") as srv:
        with pytest.raises(IgtlError, match="no peer connected"):
            srv.send(no_lock_messages("x"))
        peers = [socket.create_connection(("127.0.0.1", srv.port), timeout=2) for _ in range(2)]
        assert srv.accept(2.0) >= 1
        time.sleep(0.05)
        assert srv.send(pose_messages(_pose(), "SRV")) == 2
        for p in peers:
            with p:
                msg = read_message(p, timeout_s=2.0)
                assert msg.device_name == "SRV"
                np.testing.assert_allclose(msg.matrix, slicer_matrix(_pose()), atol=1e-4)


def test_unreachable_server_is_a_one_line_error():
    port = _free_port()  # nothing listens there
    with pytest.raises(IgtlError, match=f"127.0.0.1:{port}: cannot connect"):
        send_pose(_pose(), "127.0.0.1", port, timeout_s=1.0)


@pytest.mark.parametrize("text", ["localhost:notaport", ":18944", "host:0", "host:70000"])
def test_bad_address_is_rejected(text):
    with pytest.raises(ChicRegisterError, match="HOST:PORT"):
        parse_address(text)


def test_address_default_port_and_name_length():
    a = parse_address("10.0.0.5")
    assert (a.host, a.port) == ("10.0.0.5", 18944)
    assert check_name("CHIC") == "CHIC"
    with pytest.raises(ChicRegisterError, match="1..11 ASCII"):
        check_name("ABCDEFGHIJKL")  # + "ToolToRAS" would not fit in 20 bytes


def test_image_message_round_trip_keeps_the_slice_geometry(neuro_geometry):
    from chic_register.imaging.simulate import simulate_slice

    sim = simulate_slice(neuro_geometry, 22.0, 15.0, 30.0, 10.0, slice_thickness_mm=2.0, rng=1,
                         image_position=(-60.0, -70.0, 12.0), image_orientation=(0.0, 1.0, 0.0, 0.0, 0.0, -1.0))
    sl = sim.slice
    msg = slice_to_image_message(sl, "MRI", dtype=np.float32, scale=1.0)
    got = read_back(msg)
    (back,) = image_to_slices(got)
    np.testing.assert_allclose(back.pixels, sl.pixels, atol=1e-6)
    np.testing.assert_allclose(back.origin_mm, sl.origin_mm, atol=1e-4)
    np.testing.assert_allclose(back.col_dir, sl.col_dir, atol=1e-6)
    np.testing.assert_allclose(back.row_dir, sl.row_dir, atol=1e-6)
    assert back.pixel_spacing_mm == pytest.approx(sl.pixel_spacing_mm) and back.slice_thickness_mm == pytest.approx(2.0)
    # an image sent in RAS is turned to LPS
    ras = pyigtl.ImageMessage(got.image, ijk_to_world_matrix=FLIP @ got.ijk_to_world_matrix,
                              world_coordinate_system="ras")
    (back_ras,) = image_to_slices(read_back(ras))
    np.testing.assert_allclose(back_ras.origin_mm, sl.origin_mm, atol=1e-4)


def read_back(msg):
    a, b = socket.socketpair()
    with a, b:
        threading.Thread(target=a.sendall, args=(msg.pack(),), daemon=True).start()
        return read_message(b, timeout_s=5.0)


def test_cli_solve_sends_the_pose(tmp_path, server, neuro_geometry, neuro_geometry_file, capsys):
    from chic_register.cli.main import main
    from chic_register.imaging.simulate import simulate_slice, write_simulated

    sim = simulate_slice(neuro_geometry, 20.0, 10.0, 45.0, 10.0, noise="rician", snr=25.0, rng=4)
    img, _ = write_simulated(sim, tmp_path / "s.dcm")
    rc = main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--json",
               "--igtl", f"{server.host}:{server.port}", "--igtl-name", "ROBOT"])
    assert rc == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    T = np.array(doc["T_scanner_from_fiducial"])
    assert "chic-register: sent" in cap.err and "TRANSFORM ROBOTToRAS" in cap.err and "failed" not in cap.err
    msg = server.wait_for_message("ROBOTToRAS", timeout=5.0)
    np.testing.assert_allclose(msg.matrix, ras_matrix(T), atol=1e-3)
    msg = server.wait_for_message("ROBOT", timeout=5.0)
    np.testing.assert_allclose(msg.matrix, slicer_matrix(T), atol=1e-3)


def test_cli_solve_listen_mode_serves_the_pose_to_a_peer(tmp_path, neuro_geometry, neuro_geometry_file, capsys):
    from chic_register.cli.main import main
    from chic_register.imaging.simulate import simulate_slice, write_simulated

    sim = simulate_slice(neuro_geometry, 25.0, 5.0, 0.0, 30.0, rng=2)
    img, _ = write_simulated(sim, tmp_path / "s.dcm")
    port = _free_port()
    got = []

    def viewer():  # connects once the server listens, like Slicer's OpenIGTLinkIF in client mode
        for _ in range(200):
            try:
                conn = socket.create_connection(("127.0.0.1", port), timeout=5)
                break
            except OSError:
                time.sleep(0.02)
        with conn:
            while (m := read_message(conn, timeout_s=10.0)) is not None:
                got.append(m)

    th = threading.Thread(target=viewer, daemon=True)
    th.start()
    assert main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--igtl-listen", str(port)]) == 0
    th.join(10)
    cap = capsys.readouterr()
    out = cap.out
    assert "status: ok" in out and f"OpenIGTLink server on port {port} (1 peer)" in out
    assert f"OpenIGTLink server listening on port {port}" in cap.err
    names = [m.device_name for m in got]
    assert names == ["CHIC", "CHICToRAS", "CHICQuality", "CHIC"] and got[-1].message_type == "STATUS"
    np.testing.assert_allclose(got[1].matrix, ras_matrix(sim.truth.T_scanner_from_fiducial), atol=0.05)


def test_cli_no_lock_is_sent_as_status_and_exits_3(tmp_path, neuro_geometry_file, capsys):
    from chic_register.cli.main import main

    blank = tmp_path / "blank.npy"
    np.save(blank, np.zeros((128, 128)))
    peer = _Peer()
    try:
        rc = main(["solve", str(blank), "--geometry", str(neuro_geometry_file), "--pixel-spacing", "0.5", "0.5",
                   "--igtl", f"127.0.0.1:{peer.port}"])
        msgs = peer.wait(2)
    finally:
        peer.close()
    assert rc == 3
    status = [m for m in msgs if m.message_type == "STATUS"]
    assert len(status) == 1 and status[0].code == 4 and status[0].error_name == "no_lock"
    assert status[0].status_string and status[0].status_string in capsys.readouterr().err


def test_cli_unreachable_viewer_keeps_the_pose_and_exits_4(tmp_path, neuro_geometry, neuro_geometry_file, capsys):
    from chic_register.cli.main import main
    from chic_register.imaging.simulate import simulate_slice, write_simulated

    sim = simulate_slice(neuro_geometry, 20.0, 10.0, 45.0, 10.0, rng=4)
    img, _ = write_simulated(sim, tmp_path / "s.dcm")
    port = _free_port()
    rc = main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--igtl", f"127.0.0.1:{port}",
               "--tfm", str(tmp_path / "chic.tfm")])
    cap = capsys.readouterr()
    assert rc == 4
    assert "status: ok" in cap.out and "T_scanner_from_fiducial" in cap.out and "wrote" in cap.out
    assert (tmp_path / "chic.tfm").is_file()  # the other outputs still happen
    assert f"output failed: --igtl: OpenIGTLink server 127.0.0.1:{port}: cannot connect" in cap.err
    assert len(cap.err.strip().splitlines()) == 1


def test_bad_output_arguments_are_bad_input_before_any_work(tmp_path, neuro_geometry_file, capsys):
    from chic_register.cli.main import main

    img = tmp_path / "missing.dcm"  # never read: the outputs are checked first
    for extra, text in ((["--tfm", str(tmp_path / "nonexistent" / "dir" / "x.tfm")], "does not exist"),
                        (["--igtl", "h:1", "--igtl-listen", "5"], "give one"),
                        (["--igtl-name", "X" * 12, "--igtl", "h:1"], "ASCII characters")):
        assert main(["solve", str(img), "--geometry", str(neuro_geometry_file), *extra]) == 2
        assert text in capsys.readouterr().err
    assert not (tmp_path / "nonexistent").exists()


def test_quality_carries_predicted_tre_when_the_solver_reports_it():
    from types import SimpleNamespace

    from chic_register.outputs.deliver import quality

    sl = SimpleNamespace(residual_rms_mm=0.02, n_tubes=9)
    reg = SimpleNamespace(slices=[sl, SimpleNamespace(residual_rms_mm=0.03, n_tubes=8)],
                          to_dict=lambda: {"status": "ok", "precision": {"predicted_tre_mm": 0.123}})
    assert quality(reg) == {"residual_rms_mm": 0.03, "n_tubes": 17, "predicted_tre_mm": 0.123}
    reg = SimpleNamespace(slices=[sl], to_dict=lambda: {"status": "ok"})
    assert quality(reg) == {"residual_rms_mm": 0.02, "n_tubes": 9}
