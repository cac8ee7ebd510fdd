"""Where a pose goes besides stdout: ``--tfm``, ``--scene``, ``--overlay``, OpenIGTLink (client or server).

No lost results: every output is tried on its own; one that
fails (a closed viewer, a full disk) is reported as one line and the others
still happen; the pose itself is printed by the CLI whatever happened here,
and the exit code is :data:`EXIT_OUTPUT_FAILED` (4) when the pose is fine but
an output failed. Bad output *arguments* (a wrong suffix, a missing parent
folder, a bad address) are checked before any work and are bad input (2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from chic_register.detect.blobs import detect_blobs
from chic_register.detect.ct import detection_slice
from chic_register.errors import ChicRegisterError
from chic_register.outputs.frame import frame_report
from chic_register.outputs.overlay import draw_overlay, predicted_crossings_rc
from chic_register.util.atomic import check_parent

EXIT_OUTPUT_FAILED = 4


def find_number(doc, key: str):
    """The first finite number stored under ``key`` anywhere in a nested dict/list (None if absent)."""
    if isinstance(doc, dict):
        v = doc.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v):
            return float(v)
        doc = list(doc.values())
    if isinstance(doc, list):
        for item in doc:
            found = find_number(item, key)
            if found is not None:
                return found
    return None


def tool_pose(reg, geom) -> np.ndarray | None:
    """``T_scanner_from_tool`` (4x4) when the geometry has a tool frame."""
    if getattr(geom, "tool", None) is None:
        return None
    return np.asarray(reg.T_scanner_from_fiducial, dtype=float) @ geom.tool.T_fiducial_from_tool


def quality(reg) -> dict:
    """Pose quality for OpenIGTLink: worst slice RMS residual, tubes used, predicted TRE when known."""
    out = {"residual_rms_mm": round(max(s.residual_rms_mm for s in reg.slices), 6),
           "n_tubes": int(sum(s.n_tubes for s in reg.slices))}
    tre = find_number(reg.to_dict(), "predicted_tre_mm")
    if tre is not None:
        out["predicted_tre_mm"] = round(tre, 6)
    return out


def registration_json(reg, geom, target_F_mm=None) -> dict:
    """``solve --json``: the contract's object, plus the candidates ``assignment`` indexes, the tool and, for a
    geometry naming a stereotactic frame, ``frame_coordinates`` (:func:`~chic_register.outputs.frame.frame_report`,
    with ``target_F_mm`` in the frame when given)."""
    doc = reg.to_dict()
    for sd, res in zip(doc.get("slices", []), reg.slices):
        if res.blobs_rc is not None:
            sd["candidates_rc"] = [[round(float(r), 4), round(float(c), 4)] for r, c in np.asarray(res.blobs_rc)]
    T_tool = tool_pose(reg, geom)
    if T_tool is not None:
        doc["T_scanner_from_tool"] = [[float(v) for v in row] for row in T_tool]
        doc["tool_tip_mm"] = [float(v) for v in T_tool[:3, 3]]
    frame = frame_report(reg, geom, target_F_mm)
    if frame is not None:
        doc["frame_coordinates"] = frame
    return doc


@dataclass(frozen=True)
class OutputPlan:
    """The outputs asked for on the command line (all optional)."""

    tfm: str | None = None
    scene: str | None = None
    overlay: str | None = None
    igtl: str | None = None
    igtl_listen: int | None = None
    igtl_name: str = "CHIC"
    igtl_wait_s: float = 10.0
    geometry_path: str | None = None

    @classmethod
    def from_args(cls, args) -> "OutputPlan":
        wait = getattr(args, "igtl_wait", None)
        return cls(**{k: getattr(args, k, None) for k in ("tfm", "scene", "overlay", "igtl", "igtl_listen")},
                   igtl_name=getattr(args, "igtl_name", None) or "CHIC",
                   igtl_wait_s=10.0 if wait is None else float(wait),
                   geometry_path=getattr(args, "geometry", None))

    def check(self) -> "OutputPlan":
        """Reject bad output arguments before any work (bad input, exit 2)."""
        if self.tfm:
            from chic_register.io.transforms import (
                SUFFIXES,  # (only with --tfm: it imports SimpleITK, slow to load)
            )  # deferred: loads SimpleITK only when used (one-shot start-up)

            if Path(self.tfm).suffix.lower() not in SUFFIXES:
                raise ChicRegisterError(f"--tfm {self.tfm}: transform file must end in {', '.join(SUFFIXES)}")
            check_parent(self.tfm)
        if self.overlay:
            if not self.overlay.lower().endswith(".png"):
                raise ChicRegisterError(f"--overlay {self.overlay}: the overlay is a PNG file (name it *.png)")
            check_parent(self.overlay)
        if self.scene:
            check_parent(Path(self.scene))
        if self.igtl and self.igtl_listen is not None:
            raise ChicRegisterError("--igtl and --igtl-listen: give one (connect to a server, or be one)")
        if not (self.igtl_wait_s >= 0):
            raise ChicRegisterError(f"--igtl-wait must be >= 0 s, got {self.igtl_wait_s:g}")
        if self.igtl or self.igtl_listen is not None or self.scene:  # (the name is only used by these; and
            from chic_register.io.igtl import (  # .igtl loads pyigtl and SimpleITK)
                check_name,
                check_port,
                parse_address,
            )  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)

            if self.igtl:
                parse_address(self.igtl)
            if self.igtl_listen is not None:
                check_port(self.igtl_listen)
            check_name(self.igtl_name)
        return self

    @property
    def igtl_flag(self) -> str:
        return "--igtl-listen" if self.igtl_listen is not None else "--igtl"

    def open_link(self):
        """The OpenIGTLink end: a server listening now (peers may connect while we solve), a client, or None."""
        if self.igtl_listen is None and not self.igtl:
            return None
        from chic_register.io.igtl import (  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)
            IgtlClient,
            IgtlServer,
        )

        if self.igtl_listen is not None:
            return IgtlServer(self.igtl_listen)
        return IgtlClient(self.igtl)


@dataclass
class Delivery:
    """What happened to each output: ``done`` and ``failed`` one-line notes."""

    done: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)

    def attempt(self, what: str, action) -> None:
        try:
            note = action()
        except (ChicRegisterError, OSError, ValueError, RuntimeError) as exc:
            text = str(exc) if isinstance(exc, ChicRegisterError) else (getattr(exc, "strerror", None) or str(exc))
            if isinstance(exc, OSError) and getattr(exc, "filename", None):
                text = f"{exc.filename}: {text}"
            self.failed.append(f"{what}: {text}")
        else:
            self.done.append(note)


def _send(link, messages, wait_s: float, what: str) -> str:
    from chic_register.io.igtl import IgtlServer  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)

    if isinstance(link, IgtlServer):
        link.accept(wait_s)
    n = link.send(messages)
    return f"sent {what} to {link}" + (f" ({n} peer{'s' if n > 1 else ''})" if isinstance(link, IgtlServer) else "")


def deliver(plan: OutputPlan, reg, geom, slices, link=None) -> Delivery:
    """Write/send every planned output of a pose; failures are collected, never raised."""
    out = Delivery()
    T = reg.T_scanner_from_fiducial
    if plan.overlay:
        radius = 0.5 * max(t.diameter for t in geom.tubes)
        # the slices a volume's joint pose left out are drawn with that pose's crossings, beside its reason
        predicted = [predicted_crossings_rc(geom, T, sl) for sl in slices]
        out.attempt("--overlay", lambda: "wrote " + str(draw_overlay(plan.overlay, slices, reg, tube_radius_mm=radius,
                                                                     predicted=predicted)))
    if plan.tfm:
        from chic_register.io.transforms import (
            write_tfm,  # deferred: loads SimpleITK only when used (one-shot start-up)
        )

        out.attempt("--tfm",
                    lambda: f"wrote {write_tfm(T, plan.tfm)} (T_fiducial_from_scanner, ITK/LPS)")
    if plan.scene:
        from chic_register.outputs.scene import (
            write_scene,  # deferred: loads SimpleITK only when used (one-shot start-up)
        )

        def scene():
            mrml = write_scene(plan.scene, reg, geom, slices, name=plan.igtl_name, geometry_path=plan.geometry_path)
            beside = sorted(p.name for p in mrml.parent.iterdir() if p.name != mrml.name)
            return f"wrote {mrml} and beside it {', '.join(beside)}"

        out.attempt("--scene", scene)
    if link is not None:
        from chic_register.io.igtl import (
            pose_messages,  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)
        )

        msgs = pose_messages(T, plan.igtl_name, tool_pose(reg, geom), quality(reg))
        names = ", ".join(f"{m.message_type} {m.device_name}" for m in msgs)
        out.attempt(plan.igtl_flag, lambda: _send(link, msgs, plan.igtl_wait_s, names))
    return out


def deliver_no_lock(plan: OutputPlan, reason: str, geom, slices, link=None, refused_pose=None) -> Delivery:
    """On no lock: the overlay of the candidates (and of the crossings of ``refused_pose``, a pose that fitted but was
    refused as imprecise) and the OpenIGTLink STATUS ``no_lock``; nothing else."""
    out = Delivery()
    if plan.overlay:
        def overlay():
            d_mm = min(t.diameter for t in geom.tubes)
            seen = [detection_slice(sl, d_mm) for sl in slices]  # a CT slice's candidates are the top-hat's
            blobs = [detect_blobs(sl.pixels, sl.pixel_spacing_mm, d_mm) for sl in seen]
            predicted = None
            title = None
            if refused_pose is not None:
                T = np.asarray(refused_pose, float)
                predicted = [predicted_crossings_rc(geom, T, sl) for sl in slices]
                title = "refused as imprecise: the fitted pose's crossings (+)"
            path = draw_overlay(plan.overlay, slices, None, blobs, title=title, tube_radius_mm=0.5 * d_mm,
                                predicted=predicted)
            return f"wrote {path}"

        out.attempt("--overlay", overlay)
    if link is not None:
        from chic_register.io.igtl import (
            no_lock_messages,  # deferred: loads SimpleITK, pyigtl only when used (one-shot start-up)
        )

        out.attempt(plan.igtl_flag,
                    lambda: _send(link, no_lock_messages(reason, plan.igtl_name), plan.igtl_wait_s,
                                  f"STATUS {plan.igtl_name} (no_lock)"))
    return out
