"""Live tracking: watch a folder into which a scanner writes slices, register each new one.

The folder is polled (no extra dependency, works on network shares). A file
is registered once its size and modification time have not changed for
``settle_s`` and it reads as an image; a file that does not read yet (still
being written, truncated) is reported once and retried whenever it changes,
and otherwise after a back-off (1 s, doubling to 10 s): it is never given up.
A file rewritten after registration is registered again. Hidden files
(``.name``) and names ending in ``.tmp``, ``.part``, ``.partial``, ``~``,
``.json`` are ignored (scanners and our own writers use them for
not-yet-complete output and side files).

Latency of a pose: from the file's appearance (the earlier of the moment the
poll first saw it and its modification time then) to the pose, in
wall-clock milliseconds; ``since_write_ms`` counts from the file's last
modification instead (the part the scanner cannot hide).
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from array import array
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from chic_register.errors import ChicRegisterError, ImageReadError, NoLock
from chic_register.io.images import read_slices
from chic_register.outputs.deliver import quality, tool_pose
from chic_register.pipeline.register import register as register_slices
from chic_register.util.memory import release_freed_memory

IGNORED_SUFFIXES = (".tmp", ".part", ".partial", "~", ".json", ".swp")
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 10.0


@dataclass(frozen=True)
class TrackEvent:
    """The outcome for one file: ``status`` is ``"ok"`` (with a pose), ``"no_lock"`` or ``"error"`` (with a reason).

    ``"error"``: the file read, but registering it failed in an unexpected way
    (a bug, or an input no check caught); tracking goes on with the next file.
    """

    source: str
    status: str
    T_scanner_from_fiducial: np.ndarray | None
    slices: tuple = ()
    reason: str = ""
    latency_ms: float = float("nan")
    since_write_ms: float = float("nan")
    read_ms: float = float("nan")
    solve_ms: float = float("nan")
    igtl: str = ""  # "", "sent" or the send error
    T_scanner_from_tool: np.ndarray | None = None
    failed: tuple[str, ...] = ()  # outputs that failed (OpenIGTLink, scene), one line each

    def kept(self) -> "TrackEvent":
        """This event without its per-slice records: what a run's summary keeps of it (a tracker runs for
        hours, at 10 images a second; the pose, status and timings are a few hundred bytes)."""
        return replace(self, slices=())

    def to_dict(self) -> dict:
        out = {"source": self.source, "status": self.status}
        if self.T_scanner_from_fiducial is not None:
            out["T_scanner_from_fiducial"] = np.asarray(self.T_scanner_from_fiducial).tolist()
            if self.T_scanner_from_tool is not None:
                out["T_scanner_from_tool"] = np.asarray(self.T_scanner_from_tool).tolist()
                out["tool_tip_mm"] = np.asarray(self.T_scanner_from_tool)[:3, 3].tolist()
            out["slices"] = [s.to_dict() for s in self.slices]
        if self.reason:
            out["reason"] = self.reason
        out.update(latency_ms=round(self.latency_ms, 3), since_write_ms=round(self.since_write_ms, 3),
                   read_ms=round(self.read_ms, 3), solve_ms=round(self.solve_ms, 3))
        if self.igtl:
            out["igtl"] = self.igtl
        if self.failed:
            out["outputs_failed"] = list(self.failed)
        return out

    def text(self) -> str:
        """One human line: file, pose (angles of its slice, fiducial origin in the scanner), latency."""
        name = Path(self.source).name
        lat = f"latency {self.latency_ms:.0f} ms (solve {self.solve_ms:.0f} ms)"
        if self.status != "ok":
            return f"{name}: {self.status.replace('_', ' ')}: {self.reason}; {lat}"
        s = self.slices[0]
        o = np.asarray(self.T_scanner_from_fiducial)[:3, 3]
        line = (f"{name}: depth {s.depth_mm:.2f} mm, tilt {s.tilt_deg:.2f}, azimuth {s.azimuth_deg:.2f}, "
                f"twist {s.twist_deg:.2f} deg, rms {s.residual_rms_mm:.3f} mm; "
                f"fiducial origin ({o[0]:.2f}, {o[1]:.2f}, {o[2]:.2f}) mm; {lat}")
        if self.T_scanner_from_tool is not None:
            tip = np.asarray(self.T_scanner_from_tool)[:3, 3]
            line += f"; tool tip ({tip[0]:.2f}, {tip[1]:.2f}, {tip[2]:.2f}) mm"
        if self.failed:
            line += "; output failed: " + "; ".join(self.failed)
        return line


#: A run's summary keeps this many of its latest events in full; its counts and latency figures cover them all
#: (a tracker runs for hours at 10 images a second, and its memory must not grow with every image).
KEPT_EVENTS = 100
#: Every this many events a tracker hands freed heap memory back to the OS (a few ms; see
#: :mod:`chic_register.util.memory`), so its resident size stays flat over hours.
TRIM_EVERY = 100


class EventLog:
    """What a tracking run keeps of its events as they come: counts, every latency, the latest few events."""

    def __init__(self):
        self.recent: deque[TrackEvent] = deque(maxlen=KEPT_EVENTS)
        self.n = 0
        self.counts: dict[str, int] = {"ok": 0, "no_lock": 0, "error": 0}
        self.outputs_failed = 0
        self.ok_latency_ms = array("d")

    def add(self, event: TrackEvent) -> None:
        self.n += 1
        self.counts[event.status] = self.counts.get(event.status, 0) + 1
        self.outputs_failed += bool(event.failed)
        if event.status == "ok":
            self.ok_latency_ms.append(event.latency_ms)
        self.recent.append(event.kept())
        if self.n % TRIM_EVERY == 0:
            release_freed_memory()

    def summary(self, pending, stopped_by: str, duration_s: float) -> "TrackSummary":
        return TrackSummary(tuple(self.recent), tuple(pending), stopped_by, duration_s, files=self.n,
                            counts=dict(self.counts), outputs_failed=self.outputs_failed,
                            ok_latency_ms=tuple(self.ok_latency_ms))


@dataclass(frozen=True)
class TrackSummary:
    """Everything one tracking run did; ``stopped_by`` is ``"max_files"``, ``"timeout"`` or ``"interrupt"``.

    ``events`` are the last :data:`KEPT_EVENTS` events (:meth:`TrackEvent.kept` copies: poses, statuses and
    timings, not the per-slice records); ``files``, ``counts`` (per status), ``outputs_failed`` and
    ``ok_latency_ms`` cover every event of the run.
    """

    events: tuple[TrackEvent, ...]
    pending: tuple[str, ...]
    stopped_by: str
    duration_s: float
    files: int = 0
    counts: dict = field(default_factory=dict)
    outputs_failed: int = 0
    ok_latency_ms: tuple[float, ...] = ()

    @property
    def n_ok(self) -> int:
        return self.counts.get("ok", 0)

    def to_dict(self) -> dict:
        lat = self.ok_latency_ms
        return {
            "status": "stopped",
            "stopped_by": self.stopped_by,
            "files": self.files,
            "ok": self.n_ok,
            "no_lock": self.counts.get("no_lock", 0),
            "errors": self.counts.get("error", 0),
            "pending": list(self.pending),
            "latency_ms": {"median": float(np.median(lat)), "max": float(np.max(lat))} if lat else None,
            "outputs_failed": self.outputs_failed,
            "duration_s": round(self.duration_s, 3),
        }

    def text(self) -> str:
        d = self.to_dict()
        line = (f"stopped ({self.stopped_by}) after {self.duration_s:.1f} s: {d['files']} files, "
                f"{d['ok']} registered, {d['no_lock']} without lock")
        if d["errors"]:
            line += f", {d['errors']} failed"
        if d["latency_ms"]:
            line += f", latency median {d['latency_ms']['median']:.0f} ms, max {d['latency_ms']['max']:.0f} ms"
        if self.outputs_failed:
            line += f"; an output failed for {self.outputs_failed} of them"
        if self.pending:
            line += f"; {len(self.pending)} unreadable file(s) pending: {', '.join(Path(p).name for p in self.pending)}"
        return line


class Publisher:
    """Sends each outcome over OpenIGTLink and writes its scene; collects failures instead of raising."""

    def __init__(self, geom, link=None, name: str = "CHIC", scene_dir=None, geometry_path=None):
        self.geom, self.link, self.name = geom, link, name
        self.scene_dir = Path(scene_dir) if scene_dir else None
        self.geometry_path = geometry_path

    def tool_pose(self, reg):
        return None if reg is None else tool_pose(reg, self.geom)

    def send(self, reg, reason: str = "") -> tuple[str, list[str]]:
        """Pose messages (or STATUS no_lock): returns ("" | "sent" | error, failures)."""
        if self.link is None:
            return "", []
        from chic_register.io.igtl import (  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)
            NoPeer,
            no_lock_messages,
            pose_messages,
        )

        try:
            if reg is None:
                self.link.send(no_lock_messages(reason, self.name))
            else:
                self.link.send(pose_messages(reg.T_scanner_from_fiducial, self.name, self.tool_pose(reg),
                                             quality(reg)))
        except NoPeer:  # our server with nobody listening yet: a viewer may connect later, nothing failed
            return "no peer connected", []
        except ChicRegisterError as exc:
            return str(exc), [str(exc)]
        return "sent", []

    def scene(self, reg, slices, stem: str) -> list[str]:
        if self.scene_dir is None or reg is None:
            return []
        from chic_register.outputs.scene import (
            write_scene,  # deferred: loads SimpleITK only when used (one-shot start-up)
        )

        try:
            write_scene(self.scene_dir / stem, reg, self.geom, slices, name=self.name,
                        geometry_path=self.geometry_path)
        except (ChicRegisterError, OSError, ValueError) as exc:
            return [f"--scene: {exc}"]
        return []


@dataclass
class _Pending:
    """Watch state of one file not registered yet (mutable, private to :func:`track`)."""

    appeared_wall: float
    sig: tuple
    changed_at: float
    failed_sig: tuple | None = None
    retry_at: float = 0.0
    retry_s: float = RETRY_FIRST_S


def _ignored(name: str) -> bool:
    return name.startswith(".") or name.lower().endswith(IGNORED_SUFFIXES)


def _scan(folder: Path) -> dict[str, tuple]:
    """``{path: (size, mtime_ns)}`` of the candidate files in ``folder``."""
    out = {}
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        raise ChicRegisterError(f"{folder}: folder disappeared") from None
    for entry in entries:
        if _ignored(entry.name):
            continue
        try:
            if not entry.is_file():
                continue
            st = entry.stat()
        except OSError:  # vanished between listing and stat
            continue
        out[entry.path] = (st.st_size, st.st_mtime_ns)
    return out


def warm_up() -> None:
    """Import the image readers now, so the first file's latency does not include loading them."""
    for name in ("pydicom", "pydicom.pixels", "PIL.Image", "PIL.PngImagePlugin", "tifffile"):
        try:
            importlib.import_module(name)
        except ImportError:
            pass


def _default_event(event: TrackEvent) -> None:
    print(event.text(), flush=True)


def _default_message(text: str) -> None:
    print(f"chic-register: {text}", file=sys.stderr, flush=True)


def track(
    folder,
    geom,
    *,
    pixel_spacing=None,
    poll_s: float = 0.05,
    settle_s: float = 0.2,
    include_existing: bool = False,
    max_files: int | None = None,
    timeout_s: float | None = None,
    igtl=None,
    igtl_name: str = "CHIC",
    link=None,
    scene_dir=None,
    geometry_path=None,
    on_event=_default_event,
    on_message=_default_message,
    register=None,
    **register_options,
) -> TrackSummary:
    """Register every new image file in ``folder`` as it arrives, until stopped.

    ``geom``: the fiducial geometry. ``pixel_spacing``: (row, col) mm for
    plain images (PNG/TIFF/NPY). Files already in the folder at the start are
    skipped unless ``include_existing``. Each file is registered on its own
    (every frame of a multi-frame file jointly) by ``register`` (default
    :func:`chic_register.pipeline.register.register`); ``on_event(TrackEvent)`` receives
    each outcome, ``on_message(str)`` each skip notice (None: silent). ``igtl``: an
    ``"HOST:PORT"`` string or :class:`~chic_register.io.igtl.IgtlAddress` to
    connect to, or ``link`` any open :mod:`~chic_register.io.igtl` end (client or
    server): each pose goes out as TRANSFORMs, quality and STATUS, each no
    lock as STATUS ``no_lock`` (a failed send is reported, tracking goes on).
    ``scene_dir``: write a Slicer scene of each pose into ``scene_dir/<file name>/``.
    Stops after ``max_files`` registered files, after ``timeout_s`` seconds,
    or on Ctrl-C (KeyboardInterrupt), and returns a :class:`TrackSummary`.
    """
    if register is None:
        register = register_slices
    on_event = on_event or (lambda event: None)
    on_message = on_message or (lambda text: None)
    folder = Path(folder)
    if not folder.is_dir():
        raise ChicRegisterError(f"{folder}: not a folder")
    if not (poll_s > 0 and settle_s >= 0):
        raise ValueError("poll_s must be > 0 and settle_s >= 0")
    sender = link
    if sender is None and igtl is not None:
        from chic_register.io.igtl import (
            IgtlClient,  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)
        )

        sender = IgtlClient(igtl)
    publish = Publisher(geom, sender, igtl_name, scene_dir, geometry_path)

    warm_up()
    start = time.monotonic()
    done: dict[str, tuple] = {} if include_existing else _scan(folder)
    pending: dict[str, _Pending] = {}
    first_poll = True
    log = EventLog()
    stopped_by = "interrupt"

    def process(path: str, state: _Pending, now: float) -> TrackEvent | None:
        t0 = time.perf_counter()
        try:
            slices = read_slices([path], pixel_spacing)
        except ImageReadError as exc:
            if state.failed_sig != state.sig:
                on_message(f"skipping {exc} (will retry)")
                state.retry_s = RETRY_FIRST_S
            else:
                state.retry_s = min(2.0 * state.retry_s, RETRY_MAX_S)
            state.failed_sig = state.sig
            state.retry_at = now + state.retry_s
            return None
        except Exception as exc:  # noqa: BLE001 - one bad file must not end the tracking
            slices, failure = None, f"{type(exc).__name__}: {exc}".splitlines()[0]
        t1 = time.perf_counter()
        status, reg, reason = "ok", None, ""
        if slices is None:
            status, reason = "error", f"cannot read: {failure}"
        else:
            try:
                reg = register(slices, geom, **register_options)
            except NoLock as exc:
                status, reason = "no_lock", exc.reason
            except Exception as exc:  # noqa: BLE001 - as above: report it, go on with the next file
                status, reason = "error", f"{type(exc).__name__}: {exc}".splitlines()[0]
        t2 = time.perf_counter()
        igtl_status, failed = publish.send(reg, reason if reg is None else "")
        wall = time.time()
        mtime = state.sig[1] / 1e9
        failed += publish.scene(reg, slices, Path(path).name)
        common = dict(
            latency_ms=1000.0 * (wall - state.appeared_wall),
            since_write_ms=1000.0 * (wall - mtime),
            read_ms=1000.0 * (t1 - t0),
            solve_ms=1000.0 * (t2 - t1),
            igtl=igtl_status,
            failed=tuple(failed),
        )
        if reg is None:
            return TrackEvent(path, status, None, (), reason, **common)
        return TrackEvent(path, "ok", reg.T_scanner_from_fiducial, tuple(reg.slices),
                          T_scanner_from_tool=publish.tool_pose(reg), **common)

    try:
        while True:
            now = time.monotonic()
            if timeout_s is not None and now - start >= timeout_s:
                stopped_by = "timeout"
                break
            seen = _scan(folder)
            for gone in set(pending) - set(seen):
                del pending[gone]
            for path in sorted(seen):
                sig = seen[path]
                if done.get(path) == sig:
                    continue
                state = pending.get(path)
                if state is None:
                    # a file there at the start (--existing) appeared when we started, not when it was written
                    wall = time.time()
                    state = pending[path] = _Pending(wall if first_poll else min(wall, sig[1] / 1e9), sig, now)
                    continue
                if state.sig != sig:
                    state.sig, state.changed_at = sig, now
                    continue
                if sig[0] == 0 or now - state.changed_at < settle_s:
                    continue
                if state.failed_sig == sig and now < state.retry_at:
                    continue
                event = process(path, state, now)
                if event is None:
                    continue
                done[path] = sig
                del pending[path]
                log.add(event)
                on_event(event)
                if max_files is not None and log.n >= max_files:
                    stopped_by = "max_files"
                    break
            if stopped_by == "max_files":
                break
            first_poll = False
            time.sleep(poll_s)
    except KeyboardInterrupt:
        stopped_by = "interrupt"
    finally:
        if sender is not None:
            sender.close()
    return log.summary(sorted(pending), stopped_by, time.monotonic() - start)
