"""Live tracking over OpenIGTLink: a scanner bridge sends IMAGE messages, the pose goes back on the same link.

``chic-register track --igtl-images HOST:PORT`` connects to the bridge
(``--igtl-images-listen PORT`` waits for it to connect instead). Every
IMAGE message is turned into slices (:func:`~chic_register.io.igtl.image_to_slices`),
registered, and answered on the same connection with the pose's messages
(TRANSFORMs ``CHIC``/``CHICToRAS`` and the tool's, STRING quality, STATUS OK) or
STATUS ``no_lock`` with the reason. Each reply carries the image's own
timestamp, so the bridge can pair replies with images.

Latency of an image: from the moment its last byte was read to the moment the
TRANSFORM was handed to the socket (``latency_ms``); ``solve_ms`` is the
registration inside it, ``read_ms`` the message decoding.
"""

from __future__ import annotations

import socket
import time

from chic_register.errors import ImageReadError, NoLock
from chic_register.io.igtl import (
    IgtlClient,
    image_to_slices,
    no_lock_messages,
    pose_messages,
    read_message,
)
from chic_register.live.folder import EventLog, Publisher, TrackEvent, TrackSummary, warm_up
from chic_register.outputs.deliver import quality, tool_pose
from chic_register.pipeline.register import register as register_slices


def _connect(connect, listen, deadline):
    """An open socket to the bridge (client: connect; server: wait for it), or None at the deadline."""
    if connect is not None:
        client = IgtlClient(connect, timeout_s=5.0)
        return client.connect(), client
    server = listen
    while deadline is None or time.monotonic() < deadline:
        if server.accept(0.2):
            return server.peers.pop(0), None
    return None, None


def track_images(geom, *, connect=None, listen=None, name: str = "CHIC", max_images: int | None = None,
                 timeout_s: float | None = None, scene_dir=None, geometry_path=None,
                 on_event=None, on_message=None, register=None, **register_options) -> TrackSummary:
    """Register every IMAGE the bridge sends and answer on the same connection, until stopped.

    ``connect``: ``"HOST:PORT"`` of the bridge; or ``listen``: an
    :class:`~chic_register.io.igtl.IgtlServer` the bridge connects to (it may
    reconnect after closing). Stops after ``max_images`` images, after
    ``timeout_s`` seconds, when a connecting bridge (client mode) closes, or on
    Ctrl-C; returns a :class:`~chic_register.live.folder.TrackSummary`.
    """
    if (connect is None) == (listen is None):
        raise ValueError("give one of connect and listen")
    if register is None:
        register = register_slices
    on_event = on_event or (lambda event: None)
    on_message = on_message or (lambda text: None)
    warm_up()
    start = time.monotonic()
    deadline = None if timeout_s is None else start + timeout_s
    log = EventLog()
    ignored: set[str] = set()
    stopped_by = "interrupt"
    sock = client = None
    publish = Publisher(geom, None, name, scene_dir, geometry_path)
    try:
        while True:
            if deadline is not None and time.monotonic() >= deadline:
                stopped_by = "timeout"
                break
            if sock is None:
                sock, client = _connect(connect, listen, deadline)
                if sock is None:
                    continue
                on_message(f"scanner bridge connected ({sock.getpeername()[0]}:{sock.getpeername()[1]})")
            try:
                msg = read_message(sock, timeout_s=0.2)
            except socket.timeout:
                continue
            except OSError as exc:
                msg = None
                on_message(f"scanner bridge connection lost ({exc})")
            if msg is None:
                sock.close()
                sock = None
                if client is not None:
                    stopped_by = "closed"
                    break
                on_message("scanner bridge closed the connection; waiting for it to reconnect")
                continue
            t_recv = time.perf_counter()
            if msg.message_type != "IMAGE":
                if msg.message_type not in ignored:
                    ignored.add(msg.message_type)
                    on_message(f"ignoring {msg.message_type} messages from the scanner bridge (only IMAGE is read)")
                continue
            n = log.n + 1
            source = f"igtl:{msg.device_name or 'IMAGE'}#{n}"
            reg, reason, slices, t1 = None, "", [], t_recv
            try:
                slices = image_to_slices(msg, source)
                t1 = time.perf_counter()
                reg = register(slices, geom, **register_options)
            except NoLock as exc:
                reason = exc.reason
            except ImageReadError as exc:
                reason = f"bad IMAGE: {exc}"
            t2 = time.perf_counter()
            replies = (no_lock_messages(reason, name, msg.timestamp) if reg is None else
                       pose_messages(reg.T_scanner_from_fiducial, name, tool_pose(reg, geom), quality(reg),
                                     msg.timestamp))
            failed = []
            try:
                sock.sendall(b"".join(m.pack() for m in replies))
            except OSError as exc:
                failed.append(f"scanner bridge: reply failed ({exc.strerror or exc})")
            t_sent = time.perf_counter()
            failed += publish.scene(reg, slices, f"image_{n:05d}")
            common = dict(latency_ms=1000.0 * (t_sent - t_recv), since_write_ms=1000.0 * (time.time() - msg.timestamp),
                          read_ms=1000.0 * (t1 - t_recv), solve_ms=1000.0 * (t2 - t1),
                          igtl="sent" if not failed else failed[0], failed=tuple(failed))
            if reg is None:
                event = TrackEvent(source, "no_lock", None, (), reason, **common)
            else:
                event = TrackEvent(source, "ok", reg.T_scanner_from_fiducial, tuple(reg.slices),
                                   T_scanner_from_tool=tool_pose(reg, geom), **common)
            log.add(event)
            on_event(event)
            if max_images is not None and log.n >= max_images:
                stopped_by = "max_files"
                break
    except KeyboardInterrupt:
        stopped_by = "interrupt"
    finally:
        if sock is not None:
            sock.close()
        if client is not None:
            client.close()
    return log.summary((), stopped_by, time.monotonic() - start)
