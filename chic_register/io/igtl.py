"""OpenIGTLink both ways: poses, status and quality out; scanner images in.

Messages (packed with ``pyigtl``; STATUS, which pyigtl lacks, is packed here)
for a pose of device name ``NAME`` (default ``CHIC``):

- TRANSFORM ``NAME``: :func:`~chic_register.io.transforms.slicer_matrix`, the
  matrix that places our ``SPACE=LPS`` models (``body.stl``, the scene's
  models) in 3D Slicer, the same the ``.tfm`` gives;
- TRANSFORM ``NAMEToRAS``: :func:`~chic_register.io.transforms.ras_matrix`, F (as
  designed) to RAS, for robot controllers that work in F;
- TRANSFORM ``NAMETool`` / ``NAMEToolToRAS``: the same two for the tool frame,
  when the geometry has a tool;
- STRING ``NAMEQuality``: JSON ``{"status", "residual_rms_mm", "n_tubes",
  "predicted_tre_mm"?, "latency_ms"?}``;
- STATUS ``NAME``: code 1 (OK) with a one-line summary on a pose; code 4
  (not found), error name ``no_lock``, the reason as its message, on no lock.

Roles: :class:`IgtlClient` connects to a listening server (3D Slicer's
OpenIGTLinkIF listens on 18944 by default; a scanner bridge); :class:`IgtlServer`
listens (``--igtl-listen PORT``) and sends to every connected peer. Sockets
have bounded timeouts; failures are one-line :class:`IgtlError` messages.
"""

from __future__ import annotations

import json
import select
import socket
import struct
import time
from dataclasses import dataclass

import numpy as np
import pyigtl

from chic_register.errors import ChicRegisterError, ImageReadError, OutputError
from chic_register.io.transforms import ras_matrix, slicer_matrix
from chic_register.model.slices import Slice

DEFAULT_PORT = 18944
MAX_DEVICE_NAME = 20  # bytes in the OpenIGTLink header
SUFFIXES = ("ToRAS", "ToolToRAS", "Tool", "Quality")
MAX_NAME = MAX_DEVICE_NAME - max(len(s) for s in SUFFIXES)
STATUS_OK = 1
STATUS_NOT_FOUND = 4
_HEADER = struct.Struct("> H 12s 20s II Q Q")


class IgtlError(OutputError):
    """Cannot reach, read from or write to an OpenIGTLink peer."""


class NoPeer(IgtlError):
    """Our server (``--igtl-listen``) has nobody connected to send to."""


@dataclass(frozen=True)
class IgtlAddress:
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_address(text: str, flag: str = "--igtl") -> IgtlAddress:
    """``"HOST:PORT"`` (or ``"HOST"``, port 18944) to an :class:`IgtlAddress`."""
    host, sep, port = str(text).rpartition(":")
    if not sep:
        host, port = str(text), str(DEFAULT_PORT)
    try:
        port_num = int(port)
    except ValueError:
        port_num = -1
    if not host or not 0 < port_num < 65536:
        raise ChicRegisterError(f"{flag} {text!r}: expected HOST:PORT with a port in 1..65535, e.g. 127.0.0.1:18944")
    return IgtlAddress(host, port_num)


def check_port(port, flag: str = "--igtl-listen") -> int:
    if not isinstance(port, int) or not 0 <= port < 65536:
        raise ChicRegisterError(f"{flag} {port!r}: expected a port in 0..65535 (0: any free port)")
    return port


def check_name(name: str) -> str:
    """A device name that leaves room for the longest suffix within the header's 20 bytes."""
    if not name or not name.isascii() or len(name) > MAX_NAME:
        raise ChicRegisterError(f"--igtl-name {name!r}: 1..{MAX_NAME} ASCII characters "
                                f"(OpenIGTLink names are {MAX_DEVICE_NAME} bytes and get suffixes like 'ToolToRAS')")
    return name


class StatusMessage(pyigtl.MessageBase):
    """OpenIGTLink STATUS: code (1 OK, 4 not found, ...), subcode, error name (20 bytes), message."""

    def __init__(self, code: int = STATUS_OK, error_name: str = "", status_string: str = "",
                 subcode: int = 0, timestamp=None, device_name=None):
        super().__init__(timestamp=timestamp, device_name=device_name)
        self._message_type = "STATUS"
        self.code, self.subcode = int(code), int(subcode)
        self.error_name, self.status_string = str(error_name), str(status_string)
        self._valid_message = True

    def content_asstring(self) -> str:
        return f"{self.code} {self.error_name}: {self.status_string}"

    def _pack_content(self) -> bytes:
        return (struct.pack("> H q 20s", self.code, self.subcode, self.error_name.encode("utf-8")[:20])
                + self.status_string.encode("utf-8") + b"\0")

    def _unpack_content(self, content: bytes) -> None:
        self.code, self.subcode, name = struct.unpack("> H q 20s", content[:30])
        self.error_name = name.rstrip(b"\0").decode("utf-8", "replace")
        self.status_string = content[30:].split(b"\0", 1)[0].decode("utf-8", "replace")


def transform_message(matrix, name: str, timestamp: float | None = None):
    return pyigtl.TransformMessage(np.asarray(matrix, dtype=float), timestamp=timestamp, device_name=name)


def pose_messages(T_scanner_from_fiducial, name: str = "CHIC", T_scanner_from_tool=None,
                  quality: dict | None = None, timestamp: float | None = None) -> list:
    """TRANSFORMs ``NAME``, ``NAMEToRAS`` (and the tool's), STRING quality, STATUS OK (see module doc)."""
    ts = time.time() if timestamp is None else timestamp
    msgs = [transform_message(slicer_matrix(T_scanner_from_fiducial), name, ts),
            transform_message(ras_matrix(T_scanner_from_fiducial), name + "ToRAS", ts)]
    if T_scanner_from_tool is not None:
        msgs += [transform_message(slicer_matrix(T_scanner_from_tool), name + "Tool", ts),
                 transform_message(ras_matrix(T_scanner_from_tool), name + "ToolToRAS", ts)]
    q = {"status": "ok", **(quality or {})}
    msgs.append(pyigtl.StringMessage(json.dumps(q), timestamp=ts, device_name=name + "Quality"))
    summary = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in q.items() if k != "status")
    msgs.append(StatusMessage(STATUS_OK, "ok", f"pose ok: {summary}", timestamp=ts, device_name=name))
    return msgs


def no_lock_messages(reason: str, name: str = "CHIC", timestamp: float | None = None) -> list:
    """STATUS (code 4, ``no_lock``, the reason) and the quality STRING saying so."""
    ts = time.time() if timestamp is None else timestamp
    return [pyigtl.StringMessage(json.dumps({"status": "no_lock", "reason": reason}), timestamp=ts,
                                 device_name=name + "Quality"),
            StatusMessage(STATUS_NOT_FOUND, "no_lock", reason, timestamp=ts, device_name=name)]


def _recv_exact(sock: socket.socket, n: int, deadline: float | None) -> bytes | None:
    """``n`` bytes, or None when the peer closed; :class:`socket.timeout` past ``deadline``."""
    buf = bytearray()
    while len(buf) < n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise socket.timeout("timed out")
            sock.settimeout(left)
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def read_message(sock: socket.socket, timeout_s: float | None = None, body_timeout_s: float = 5.0):
    """The next message on ``sock`` (pyigtl message or :class:`StatusMessage`; unknown types as
    :class:`pyigtl.MessageBase` with its type and name), None when the peer closed, or
    :class:`socket.timeout` when no header arrived within ``timeout_s``."""
    head = _recv_exact(sock, _HEADER.size, None if timeout_s is None else time.monotonic() + timeout_s)
    if head is None:
        return None
    fields = pyigtl.MessageBase.parse_header(head)
    body = _recv_exact(sock, fields["body_size"], time.monotonic() + body_timeout_s)
    if body is None:
        return None
    kind = fields["message_type"]
    msg = StatusMessage() if kind == "STATUS" else pyigtl.MessageBase.create_message(kind)
    if msg is None:
        msg = pyigtl.MessageBase(device_name=fields["device_name"])
        msg._message_type = kind
        return msg
    msg.unpack(fields, body)
    return msg


class IgtlClient:
    """One client connection to ``address``; connects on first use, reconnects on the next use after a failure.

    Use as a context manager; ``timeout_s`` bounds connecting and each send.
    """

    def __init__(self, address: IgtlAddress | str, timeout_s: float = 2.0):
        self.address = parse_address(address) if isinstance(address, str) else address
        self.timeout_s = float(timeout_s)
        self._sock: socket.socket | None = None

    def __str__(self) -> str:
        return f"OpenIGTLink server {self.address}"

    def connect(self) -> socket.socket:
        if self._sock is None:
            try:
                self._sock = socket.create_connection((self.address.host, self.address.port), timeout=self.timeout_s)
                self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError as exc:
                raise IgtlError(f"{self}: cannot connect ({exc.strerror or exc})") from None
        return self._sock

    def send(self, messages) -> int:
        """Send ``messages`` (one or a list); returns 1 (peers reached); :class:`IgtlError` on failure."""
        data = b"".join(m.pack() for m in (messages if isinstance(messages, (list, tuple)) else [messages]))
        sock = self.connect()
        try:
            sock.settimeout(self.timeout_s)
            sock.sendall(data)
        except OSError as exc:
            self.close()
            raise IgtlError(f"{self}: send failed ({exc.strerror or exc})") from None
        return 1

    def receive(self, timeout_s: float | None = None):
        """The next message from the server (None: it closed); ``socket.timeout`` when none came."""
        try:
            msg = read_message(self.connect(), timeout_s)
        except socket.timeout:
            raise
        except (OSError, struct.error, ValueError) as exc:
            self.close()
            raise IgtlError(f"{self}: receive failed ({exc})") from None
        if msg is None:
            self.close()
        return msg

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


class IgtlServer:
    """A listening socket (``--igtl-listen PORT``) that sends every message to each connected peer.

    Peers are accepted whenever :meth:`accept` or :meth:`send` runs (no
    thread); a peer that fails a send is dropped. ``port`` 0 picks a free
    port (:attr:`port` tells which).
    """

    def __init__(self, port: int, host: str = "0.0.0.0", timeout_s: float = 2.0):
        self.timeout_s = float(timeout_s)
        try:
            self._listener = socket.create_server((host, check_port(port)), reuse_port=False)
        except OSError as exc:
            raise IgtlError(f"--igtl-listen {port}: cannot listen ({exc.strerror or exc})") from None
        self._listener.setblocking(False)
        self.host, self.port = host, self._listener.getsockname()[1]
        self.peers: list[socket.socket] = []

    def __str__(self) -> str:
        return f"OpenIGTLink server on port {self.port}"

    def accept(self, wait_s: float = 0.0) -> int:
        """Accept pending peers, waiting up to ``wait_s`` for a first one when there is none; returns the count."""
        deadline = time.monotonic() + wait_s
        while True:
            ready, _, _ = select.select([self._listener], [], [], 0 if self.peers else max(0.0, deadline - time.monotonic()))
            if not ready:
                return len(self.peers)
            try:
                conn, _ = self._listener.accept()
            except BlockingIOError:
                continue
            conn.setblocking(True)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.peers.append(conn)

    def send(self, messages) -> int:
        """Send to every peer (accepting new ones first); returns how many got it; :class:`IgtlError` if none."""
        data = b"".join(m.pack() for m in (messages if isinstance(messages, (list, tuple)) else [messages]))
        self.accept()
        sent = 0
        for peer in list(self.peers):
            try:
                peer.settimeout(self.timeout_s)
                peer.sendall(data)
                sent += 1
            except OSError:
                self.peers.remove(peer)
                peer.close()
        if not sent:
            raise NoPeer(f"{self}: no peer connected")
        return sent

    def close(self) -> None:
        for peer in self.peers:
            peer.close()
        self.peers = []
        self._listener.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def send_pose(T_scanner_from_fiducial, host: str, port: int, name: str = "CHIC", timeout_s: float = 2.0,
              T_scanner_from_tool=None, quality: dict | None = None) -> None:
    """Connect to the server at ``host:port``, send one pose's messages, close."""
    with IgtlClient(IgtlAddress(host, int(port)), timeout_s=timeout_s) as client:
        client.send(pose_messages(T_scanner_from_fiducial, name, T_scanner_from_tool, quality))


def image_to_slices(msg, source: str | None = None) -> list:
    """The k-planes of a pyigtl IMAGE message as :class:`~chic_register.model.slices.Slice` objects (scanner = LPS).

    Columns run along i, rows along j (OpenIGTLink's ijk); a RAS image is
    turned to LPS; each plane's thickness is the k spacing.
    """
    name = source or f"igtl:{msg.device_name or 'IMAGE'}"
    img = np.asarray(msg.image)
    if img.ndim == 4:
        if img.shape[3] != 1:
            raise ImageReadError(name, f"IMAGE has {img.shape[3]} components; a scalar image is needed")
        img = img[..., 0]
    M = np.asarray(msg.ijk_to_world_matrix, dtype=float)
    if getattr(msg, "world_coordinate_system", "lps") == "ras":
        M = np.diag([-1.0, -1.0, 1.0, 1.0]) @ M
    spacing = np.linalg.norm(M[:3, :3], axis=0)
    if img.ndim != 3 or min(img.shape[1:]) < 8 or not np.all(spacing > 0) or not np.all(np.isfinite(M)):
        raise ImageReadError(name, f"IMAGE of shape {img.shape} with spacing {spacing.round(4).tolist()} "
                             "is not a slice (need at least 8x8 pixels and a finite, non-zero spacing)")
    col_dir, row_dir = M[:3, 0] / spacing[0], M[:3, 1] / spacing[1]
    out = []
    for k in range(img.shape[0]):
        origin = M[:3, 3] + k * M[:3, 2]
        out.append(Slice(np.asarray(img[k], dtype=float), (float(spacing[1]), float(spacing[0])), origin,
                         col_dir, row_dir, float(spacing[2]), name if img.shape[0] == 1 else f"{name}[{k}]"))
    return out


def slice_to_image_message(sl, name: str = "MRI", dtype=np.int16, scale: float = 1000.0,
                           timestamp: float | None = None):
    """A :class:`~chic_register.model.slices.Slice` as an LPS IMAGE message (what a scanner bridge sends).

    Pixels are multiplied by ``scale`` and stored as ``dtype`` (int16, as
    MR magnitudes usually are); the inverse of :func:`image_to_slices`.
    """
    M = np.eye(4)
    M[:3, 0] = np.asarray(sl.col_dir) * sl.pixel_spacing_mm[1]
    M[:3, 1] = np.asarray(sl.row_dir) * sl.pixel_spacing_mm[0]
    M[:3, 2] = sl.normal * (sl.slice_thickness_mm if sl.slice_thickness_mm > 0 else 1.0)
    M[:3, 3] = sl.origin_mm
    pixels = np.asarray(sl.pixels, dtype=float) * scale
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        pixels = np.clip(np.rint(pixels), info.min, info.max)
    return pyigtl.ImageMessage(pixels.astype(dtype)[None], ijk_to_world_matrix=M, world_coordinate_system="lps",
                               timestamp=timestamp, device_name=name)
