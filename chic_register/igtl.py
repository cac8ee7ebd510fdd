"""Send a registration as an OpenIGTLink TRANSFORM message (3D Slicer, robot controllers).

``--igtl HOST:PORT`` means: connect as a *client* to an OpenIGTLink server
listening at HOST:PORT (3D Slicer's OpenIGTLinkIF module listens as a server
by default, port 18944) and send one TRANSFORM message per pose.

The matrix sent is ``T_RAS_from_fiducial = diag(-1, -1, 1, 1) @
T_scanner_from_fiducial``: it maps F points (mm) to RAS points (mm), the
convention of Slicer's scene. In Slicer the message becomes a linear
transform node whose "to parent" matrix is this one, so a model in F placed
under it appears where the fiducial is.

Messages are packed by ``pyigtl`` (``pyigtl.TransformMessage``) and written
on a plain TCP socket: connecting and sending have bounded timeouts and
failures are one-line :class:`IgtlError` messages, where pyigtl's own
client thread would retry forever in the background.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

import numpy as np
import pyigtl

from .errors import ChicRegisterError

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
DEFAULT_PORT = 18944


class IgtlError(ChicRegisterError):
    """Cannot reach or write to the OpenIGTLink server."""


@dataclass(frozen=True)
class IgtlAddress:
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_address(text: str) -> IgtlAddress:
    """``"HOST:PORT"`` (or ``"HOST"``, port 18944) to an :class:`IgtlAddress`."""
    host, sep, port = str(text).rpartition(":")
    if not sep:
        host, port = str(text), str(DEFAULT_PORT)
    try:
        port_num = int(port)
    except ValueError:
        port_num = -1
    if not host or not 0 < port_num < 65536:
        raise ChicRegisterError(f"--igtl {text!r}: expected HOST:PORT with a port in 1..65535, e.g. 127.0.0.1:18944")
    return IgtlAddress(host, port_num)


def ras_matrix(T_scanner_from_fiducial) -> np.ndarray:
    """The matrix of the TRANSFORM message: F -> RAS (4x4)."""
    T = np.asarray(T_scanner_from_fiducial, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {T.shape}")
    return LPS_TO_RAS @ T


def transform_message(T_scanner_from_fiducial, name: str = "CHIC", timestamp: float | None = None):
    """A ``pyigtl.TransformMessage`` carrying the pose in RAS under device name ``name``."""
    return pyigtl.TransformMessage(ras_matrix(T_scanner_from_fiducial), timestamp=timestamp, device_name=name)


class IgtlSender:
    """One client connection that sends TRANSFORM messages; reconnects on the next send after a failure.

    Use as a context manager; ``timeout_s`` bounds connecting and each send.
    """

    def __init__(self, address: IgtlAddress | str, name: str = "CHIC", timeout_s: float = 2.0):
        self.address = parse_address(address) if isinstance(address, str) else address
        self.name = name
        self.timeout_s = float(timeout_s)
        self._sock: socket.socket | None = None

    def _connect(self) -> socket.socket:
        if self._sock is None:
            try:
                self._sock = socket.create_connection((self.address.host, self.address.port), timeout=self.timeout_s)
            except OSError as exc:
                raise IgtlError(f"OpenIGTLink server {self.address}: cannot connect ({exc.strerror or exc})") from None
        return self._sock

    def send(self, T_scanner_from_fiducial) -> None:
        """Send one pose (F -> scanner LPS, 4x4); raises :class:`IgtlError` on failure."""
        data = transform_message(T_scanner_from_fiducial, self.name).pack()
        sock = self._connect()
        try:
            sock.sendall(data)
        except OSError as exc:
            self.close()
            raise IgtlError(f"OpenIGTLink server {self.address}: send failed ({exc.strerror or exc})") from None

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def send_pose(T_scanner_from_fiducial, host: str, port: int, name: str = "CHIC", timeout_s: float = 2.0) -> None:
    """Connect to the server at ``host:port``, send one TRANSFORM message, close."""
    with IgtlSender(IgtlAddress(host, int(port)), name=name, timeout_s=timeout_s) as sender:
        sender.send(T_scanner_from_fiducial)
