"""``chic-design build``: from a spec to a checked export folder, written atomically.

Order: validate the spec (before any CAD work) -> geometry -> feasibility
(refuse an infeasible design unless forced) -> CAD -> export into a temporary
folder inside ``out_root`` -> verify the files -> pictures -> report -> replace
``out_root/<name>`` in one rename. The pictures (preview, tilt plot) need only
the geometry and are drawn in a worker process while the CAD work runs. On any
failure the temporary folder is removed and an earlier export is left as it was.
"""

from __future__ import annotations

import functools
import json
import multiprocessing
import os
import re
import shutil
import sys
import tempfile
import time
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from build123d import Mesher, export_step

from chic_register.model.geometry import write_geometry

from .cad import FiducialParts, build_parts
from .errors import InfeasibleDesign
from .feasibility import check_design
from .layout import design_geometry
from .lifeline import die_with_parent
from .preview import precision_job, preview_job, tilt_plot_job
from .printability import HARD_CODES
from .report import build_report
from .spec import load_spec, spec_sha256
from chic_register.io.stl import declare_space
from .verify import STL_ANGULAR_TOLERANCE_RAD, STL_TOLERANCE_MM, VerifyResult, verify_export

TMP_PREFIX = ".{name}.tmp-"  # + "<owner pid>-<random>"
OLD_PREFIX = ".{name}.old-"
_OWNER = re.compile(r"^(\d+)-[A-Za-z0-9_]+$")  # owner pid, then mkdtemp's random letters


@dataclass(frozen=True)
class BuildResult:
    """A finished build: its folder, the output checks and per-step wall times (s)."""

    folder: Path
    checks: VerifyResult
    timings: dict[str, float] = field(default_factory=dict)
    feasible: bool | None = None
    wall_s: float = 0.0

    def summary_text(self) -> str:
        n = len(self.checks.checks)
        lines = [
            f"built {self.folder} in {self.wall_s:.1f} s: {n}/{n} output checks passed",
            "files: " + ", ".join(sorted(p.name for p in self.folder.iterdir())),
        ]
        if self.feasible is False:
            lines.append("WARNING: the design is infeasible (built with --force); see report.md")
        return "\n".join(lines)


class _Steps:
    """Times each step; with ``progress`` prints one line per finished step with its time to stderr.

    A failed step prints nothing: the CLI's one-line error message follows.
    """

    def __init__(self, progress: bool, total: int):
        self.progress = progress
        self.total = total
        self.timings: dict[str, float] = {}

    @contextmanager
    def step(self, name: str):
        t0 = time.perf_counter()
        yield
        dt = time.perf_counter() - t0
        self.timings[name] = dt
        if self.progress:
            print(f"chic-design: [{len(self.timings)}/{self.total}] {name} {dt:.2f} s", file=sys.stderr, flush=True)


def design_parts(spec, geometry) -> FiducialParts:
    """The printed parts of any spec family (CHIC: :func:`build_parts`; Z-frame: its own module)."""
    if getattr(spec, "family", "chic") == "zframe":
        from .zframe_cad import build_zframe_parts

        return build_zframe_parts(spec, geometry)
    return build_parts(spec, geometry)


def export_parts(parts: FiducialParts, folder: Path, name: str) -> list[str]:
    """Write each part as STL, STEP and 3MF (mm, named) plus ``assembly.step``; returns file names."""
    written = []
    for part_name, part in parts.items():
        part.label = part_name
        if not export_step(part, folder / f"{part_name}.step"):
            raise OSError(f"{folder / part_name}.step: STEP export failed")
        # one tessellation for both mesh files: the STL and the 3MF hold the same triangles
        mesher = Mesher()
        mesher.add_shape(part, linear_deflection=STL_TOLERANCE_MM,
                         angular_deflection=STL_ANGULAR_TOLERANCE_RAD, part_number=part_name)
        mesher.write(str(folder / f"{part_name}.3mf"))
        mesher.write(str(folder / f"{part_name}.stl"))
        declare_space(folder / f"{part_name}.stl")  # SPACE=LPS: Slicer reads F as the .tfm expects
        written += [f"{part_name}.stl", f"{part_name}.step", f"{part_name}.3mf"]
    if not export_step(parts.assembly(name), folder / "assembly.step"):
        raise OSError(f"{folder}/assembly.step: STEP export failed")
    return written + ["assembly.step"]


def _overlap_mm3(a, b) -> float:
    """Exact volume (mm^3) shared by two CAD parts (0 when they only touch)."""
    common = a.intersect(b)
    return 0.0 if common is None else float(common.volume)


def _default_permissions(folder: Path) -> None:
    """mkdtemp/mkstemp make private (0700/0600) entries; give the export the usual umask modes."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(folder, 0o777 & ~umask)
    for path in folder.iterdir():
        if path.is_file():
            os.chmod(path, 0o666 & ~umask)


def _pid_alive(pid: int) -> bool:
    """True when a process ``pid`` exists (also when it belongs to another user)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(out_root, name: str) -> list[Path]:
    """Remove the temporary folders of earlier builds of ``name`` whose owner process is dead.

    A build killed hard (SIGKILL, power loss) cannot clean up. Its
    ``.<name>.tmp-<pid>-*`` folder is removed here; a ``.<name>.old-<pid>-*``
    folder (the previous export, moved aside just before the final rename) is
    renamed back to ``<name>`` if that is missing, else removed. Folders of a
    live process (a build running now) are left alone. Returns what was removed.
    """
    out_root = Path(out_root)
    removed = []
    try:
        entries = sorted(out_root.iterdir(), key=lambda p: p.stat().st_mtime if p.exists() else 0.0)
    except OSError:
        return removed
    for path in entries:
        for prefix in (TMP_PREFIX.format(name=name), OLD_PREFIX.format(name=name)):
            if not path.name.startswith(prefix) or not path.is_dir():
                continue
            m = _OWNER.match(path.name[len(prefix):])
            if m is None or _pid_alive(int(m.group(1))):
                continue
            final = out_root / name
            if prefix.endswith(".old-") and not final.exists():
                os.rename(path, final)  # the kill came between the two renames: restore the export
            else:
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
    return removed


def _owned_mkdtemp(prefix: str, parent: Path) -> Path:
    """``mkdtemp`` with this process's pid in the name, so a later build can tell a stale folder."""
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-", dir=parent))


def _replace_folder(tmp: Path, final: Path) -> None:
    """Put ``tmp`` at ``final``: move an old ``final`` aside, rename ``tmp`` in, delete the old one."""
    old = None
    if final.exists():
        old = _owned_mkdtemp(OLD_PREFIX.format(name=final.name), final.parent)
        os.rmdir(old)
        os.rename(final, old)
    try:
        os.rename(tmp, final)
    except BaseException:
        if old is not None:
            os.rename(old, final)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


class _Pictures:
    """Picture jobs (preview, tilt plot): in a worker process, or here when collected.

    The pictures need only the geometry objects and the feasibility report, so
    by default a worker process (the second core) draws them while this
    process does the CAD work. Each job returns its wall time (s).
    """

    def __init__(self, in_worker: bool):
        self.executor = (ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=die_with_parent, initargs=(os.getpid(),))
                         if in_worker else None)
        self.jobs: list[tuple[str, object]] = []

    def submit(self, name: str, fn, *args) -> None:
        job = self.executor.submit(fn, *args) if self.executor else functools.partial(fn, *args)
        self.jobs.append((name, job))

    def collect(self) -> dict[str, float]:
        return {name: job.result() if isinstance(job, Future) else job() for name, job in self.jobs}

    def close(self, cancel: bool = False) -> None:
        """Wait for the worker (so nothing writes into the folder afterwards) and stop it."""
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=cancel)
            self.executor = None


def build_design(spec_path, out_root="exports", force: bool = False, progress: bool = True,
                 pictures_in_worker: bool = True) -> BuildResult:
    """Build the design in ``spec_path`` into ``out_root/<name>/`` and check the files.

    Raises :class:`~chic_design.errors.SpecError` (bad spec, before any CAD work),
    :class:`~chic_design.errors.InfeasibleDesign` (unless ``force``) or
    :class:`~chic_design.errors.BuildCheckError` (an output check failed); in
    every failure ``out_root/<name>`` is left as it was. ``pictures_in_worker``
    renders the preview and tilt plot in a second process, in parallel.
    """
    t_start = time.perf_counter()
    steps = _Steps(progress, total=9)
    with steps.step("spec"):
        spec = load_spec(spec_path)
    with steps.step("geometry"):
        source = {"spec": str(spec_path), "spec_sha256": spec_sha256(spec_path)}
        geometry = design_geometry(spec, source=source)
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    final = out_root / spec.name
    remove_stale_temporaries(out_root, spec.name)
    tmp = _owned_mkdtemp(TMP_PREFIX.format(name=spec.name), out_root)
    pictures = _Pictures(pictures_in_worker)
    try:
        pictures.submit("preview", preview_job, geometry, tmp)
        with steps.step("feasibility"):
            feasibility = check_design(spec)
            hard = [v for v in feasibility.violations if v.code in HARD_CODES]
            if hard or (not feasibility.feasible and not force):
                # the printability rules make the build fail or its output useless: --force cannot help
                raise InfeasibleDesign(spec_path, hard or feasibility.violations, forceable=not hard)
            pictures.submit("tilt plot", tilt_plot_job, feasibility, tmp)
            pictures.submit("precision", precision_job, geometry, spec.imaging.pixel_size,
                            spec.imaging.slice_thickness, tmp)
        with steps.step("CAD model"):
            parts = design_parts(spec, geometry)
            volumes = {name: float(p.volume) for name, p in parts.items()}
        with steps.step("export STL/STEP/3MF"):
            write_geometry(geometry, tmp / "geometry.yaml")
            files = export_parts(parts, tmp, spec.name) + ["geometry.yaml"]
            (tmp / "feasibility.json").write_text(json.dumps(feasibility.to_dict(), indent=2), encoding="utf-8")
            files.append("feasibility.json")
        with steps.step("verify outputs"):
            overlaps = {cap: _overlap_mm3(parts.body, getattr(parts, cap)) for cap in ("cap_top", "cap_bottom")}
            checks = verify_export(tmp, volumes, overlaps)
        with steps.step("preview and tilt plot"):
            picture_times = pictures.collect()
            files += ["preview.png", "tilt_limits.png", "precision.md"]
            files += ["precision.png"] if (tmp / "precision.png").is_file() else []
        with steps.step("report"):
            files.append("report.md")
            timings = {**steps.timings, **{f"{k} (parallel)": v for k, v in picture_times.items()}}
            text = build_report(spec, spec_path, geometry, volumes, checks, feasibility.markdown(),
                                timings, files, (tmp / "precision.md").read_text(encoding="utf-8"))
            (tmp / "report.md").write_text(text, encoding="utf-8")
        with steps.step("replace export folder"):
            _default_permissions(tmp)
            _replace_folder(tmp, final)
    except BaseException:
        pictures.close(cancel=True)  # no writes into tmp after this
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        pictures.close()
    timings = {**steps.timings, **{f"{k} (parallel)": v for k, v in picture_times.items()}}  # + last step
    return BuildResult(final.resolve(), checks, timings, feasibility.feasible,
                       wall_s=time.perf_counter() - t_start)
