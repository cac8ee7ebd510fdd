"""OpenIGTLink output: a real pyigtl server on loopback receives the pose in RAS."""

from __future__ import annotations

import signal
import socket

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from chic_register.errors import ChicRegisterError  # noqa: E402
from chic_register.igtl import IgtlError, IgtlSender, parse_address, ras_matrix, send_pose  # noqa: E402
from chic_register.pose import rigid, rot_y, rot_z  # noqa: E402


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


def _pose():
    return rigid(rot_z(30.0) @ rot_y(20.0) @ rot_z(-45.0), (12.5, -40.0, 7.25))


def test_ras_matrix_flips_first_two_rows():
    T = _pose()
    M = ras_matrix(T)
    np.testing.assert_allclose(M[:2], -T[:2])
    np.testing.assert_allclose(M[2:], T[2:])
    # F origin in LPS (x, y, z) is at RAS (-x, -y, z)
    np.testing.assert_allclose(M[:3, 3], [-12.5, 40.0, 7.25])


def test_server_receives_transform_in_ras(server):
    T = _pose()
    send_pose(T, server.host, server.port, name="CHICTEST", timeout_s=2.0)
    msg = server.wait_for_message("CHICTEST", timeout=5.0)
    assert msg is not None, "no message received within 5 s"
    assert msg.message_type == "TRANSFORM"
    expected = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T
    np.testing.assert_allclose(msg.matrix, expected, atol=1e-4)  # float32 on the wire


def test_sender_sends_several_poses_on_one_connection(server):
    poses = [_pose(), rigid(rot_z(90.0), (1.0, 2.0, 3.0))]
    with IgtlSender(parse_address(f"{server.host}:{server.port}"), name="TRK") as sender:
        for T in poses:
            sender.send(T)
            msg = server.wait_for_message("TRK", timeout=5.0)
            assert msg is not None
            np.testing.assert_allclose(msg.matrix, ras_matrix(T), atol=1e-4)


def test_unreachable_server_is_a_one_line_error():
    port = _free_port()  # nothing listens there
    with pytest.raises(IgtlError, match=f"127.0.0.1:{port}: cannot connect"):
        send_pose(_pose(), "127.0.0.1", port, timeout_s=1.0)


@pytest.mark.parametrize("text", ["localhost:notaport", ":18944", "host:0", "host:70000"])
def test_bad_address_is_rejected(text):
    with pytest.raises(ChicRegisterError, match="HOST:PORT"):
        parse_address(text)


def test_address_default_port():
    a = parse_address("10.0.0.5")
    assert (a.host, a.port) == ("10.0.0.5", 18944)


def test_cli_solve_sends_the_pose(tmp_path, server, neuro_geometry, neuro_geometry_file, capsys):
    import json

    from chic_register.cli import main
    from chic_register.simulate import simulate_slice, write_simulated

    sim = simulate_slice(neuro_geometry, 20.0, 10.0, 45.0, 10.0, noise="rician", snr=25.0, rng=4)
    img, _ = write_simulated(sim, tmp_path / "s.dcm")
    rc = main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--json",
               "--igtl", f"{server.host}:{server.port}", "--igtl-name", "ROBOT"])
    assert rc == 0
    T = np.array(json.loads(capsys.readouterr().out)["T_scanner_from_fiducial"])
    msg = server.wait_for_message("ROBOT", timeout=5.0)
    assert msg is not None
    np.testing.assert_allclose(msg.matrix, ras_matrix(T), atol=1e-3)
