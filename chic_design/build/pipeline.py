"""``chic-design build``: from a spec to a checked export folder, written atomically, for any family.

Order: validate the spec (before any CAD work) -> geometry -> feasibility
(refuse an infeasible design unless forced) -> CAD -> export into a temporary
folder inside ``out_root`` -> verify the files -> pictures -> fill guide -> report -> replace
``out_root/<name>`` in one rename. The pictures (preview, tilt plot) need only
the geometry and are drawn in a worker process while the CAD work runs. On any
failure the temporary folder is removed and an earlier export is left as it was.
The family of the spec (:func:`chic_design.families.family_of`) makes the
geometry, checks it and makes the parts; everything else is the same for all.
For hardware the family does not print (:meth:`~chic_design.families.base.Family.printed`:
a commercial frame described for the solver) the part steps are skipped: the
folder holds geometry.yaml, feasibility.json, the pictures and the report.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from chic_design.build.folders import (
    TMP_PREFIX,
    default_permissions,
    owned_mkdtemp,
    remove_stale_temporaries,
    replace_folder,
)
from chic_design.build.workers import PictureJobs
from chic_design.cad.export import export_parts
from chic_design.cad.parts import with_resin_vents
from chic_design.errors import ChannelsNotPrintable, InfeasibleDesign
from chic_design.families import family_of
from chic_design.feasibility.printability import HARD_CODES
from chic_design.printing.export import PLATE_NAME, PRINTCHECK_FILES, run_printcheck, write_print_plate
from chic_design.printing.slicer import find_slicer
from chic_design.progress import Steps, status
from chic_design.report.fill_guide import fill_guide, write_fill_guide
from chic_design.report.markdown import build_report
from chic_design.report.pictures import precision_job, preview_job, tilt_plot_job
from chic_design.spec import load_spec, spec_sha256
from chic_design.verify import VerifyResult, verify_export
from chic_register.model.geometry import write_geometry

#: The steps :func:`build_design` times (and shows with ``progress``), in order.
STEPS = ("spec", "geometry", "feasibility", "CAD model", "export STL/STEP/3MF", "verify outputs", "print plate",
         "print check", "preview and tilt plot", "fill guide", "report", "replace export folder")


@dataclass(frozen=True)
class BuildResult:
    """A finished build: its folder, the files written in it, the output checks and per-step wall times (s)."""

    folder: Path
    checks: VerifyResult
    timings: dict[str, float] = field(default_factory=dict)
    feasible: bool | None = None
    wall_s: float = 0.0
    files: tuple[str, ...] = ()
    print_failures: str = ""

    def summary_text(self) -> str:
        n = len(self.checks.checks)
        lines = [
            f"built {self.folder} in {self.wall_s:.1f} s: {n}/{n} output checks passed",
            "files: " + ", ".join(sorted(p.name for p in self.folder.iterdir())),
        ]
        if self.feasible is False:
            lines.append("WARNING: the design is infeasible (built with --force); see report.md")
        if self.print_failures:
            lines.append(f"WARNING: the print check failed (built with --force): {self.print_failures}")
        return "\n".join(lines)


def overlap_mm3(a, b) -> float:
    """Exact volume (mm^3) shared by two CAD parts (0 when they only touch)."""
    common = a.intersect(b)
    return 0.0 if common is None else float(common.volume)


def build_design(spec_path, out_root="exports", force: bool = False, progress: bool = True,
                 pictures_in_worker: bool = True, printcheck: bool | None = None) -> BuildResult:
    """Build the design in ``spec_path`` into ``out_root/<name>/`` and check the files.

    Raises :class:`~chic_design.errors.SpecError` (bad spec, before any CAD work),
    :class:`~chic_design.errors.InfeasibleDesign` (unless ``force``) or
    :class:`~chic_design.errors.BuildCheckError` (an output check failed); in
    every failure ``out_root/<name>`` is left as it was. ``pictures_in_worker``
    renders the preview and tilt plot in a second process, in parallel.
    ``printcheck`` slices the plate and checks every channel in the toolpaths
    (None: when ``prusa-slicer`` is on the PATH; True: required; False: skipped);
    a channel the toolpaths close or narrow fails the build
    (:class:`~chic_design.errors.ChannelsNotPrintable`).
    """
    t_start = time.perf_counter()
    steps = Steps(progress, total=len(STEPS))
    with steps.step("spec"):
        spec = load_spec(spec_path)
        family = family_of(spec)
        printed = family.printed(spec)
    with steps.step("geometry"):
        source = {"spec": str(spec_path), "spec_sha256": spec_sha256(spec_path)}
        geometry = family.geometry(spec, source=source)
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    final = out_root / spec.name
    remove_stale_temporaries(out_root, spec.name)
    tmp = owned_mkdtemp(TMP_PREFIX.format(name=spec.name), out_root)
    pictures = PictureJobs(pictures_in_worker)
    try:
        pictures.submit("preview", preview_job, geometry, tmp)
        with steps.step("feasibility"):
            feasibility = family.check(spec)
            hard = [v for v in feasibility.violations if v.code in HARD_CODES]
            if hard or (not feasibility.feasible and not force):
                # the printability rules make the build fail or its output useless: --force cannot help
                raise InfeasibleDesign(spec_path, hard or feasibility.violations, forceable=not hard)
            pictures.submit("tilt plot", tilt_plot_job, feasibility, tmp)
            pictures.submit("precision", precision_job, geometry, spec.imaging.pixel_size,
                            spec.imaging.slice_thickness, tmp)
        with steps.step("CAD model"):
            parts, volumes = None, {}
            if printed:
                parts = family.parts(spec, geometry)
                if spec.print.printer == "resin":
                    parts = with_resin_vents(parts, geometry)
                volumes = {name: float(p.volume) for name, p in parts.items()}
        cap_dims = parts.cap_dims if parts is not None else None
        with steps.step("export STL/STEP/3MF"):
            write_geometry(geometry, tmp / "geometry.yaml")
            files = (export_parts(parts, tmp, spec.name) if parts is not None else []) + ["geometry.yaml"]
            (tmp / "feasibility.json").write_text(json.dumps(feasibility.to_dict(), indent=2), encoding="utf-8")
            files.append("feasibility.json")
        with steps.step("verify outputs"):
            overlaps = ({cap: overlap_mm3(parts.body, getattr(parts, cap)) for cap in ("cap_top", "cap_bottom")}
                        if parts is not None else {})
            checks = verify_export(tmp, volumes, overlaps, printed=printed)
        with steps.step("print plate"):
            plate = write_print_plate(tmp, spec, geometry, cap_dims) if printed else None
            files += [PLATE_NAME] if printed else []
            if plate is not None and not plate.fits_bed and progress:
                status(f"the parts do not fit on the printer's bed together; {PLATE_NAME} is laid out on a "
                       f"{plate.bed_mm[0]:g} x {plate.bed_mm[1]:g} mm bed: print them one at a time")
        with steps.step("print check"):
            print_result, print_note = None, ""
            slicer = find_slicer()
            if not printed:
                print_note = "nothing is printed (commercial hardware)"
            elif printcheck is False:
                print_note = "skipped (printcheck off)"
            elif slicer is None and printcheck is None:
                print_note = "skipped: prusa-slicer is not on the PATH (install PrusaSlicer, then run chic-design printcheck)"
            else:
                print_result = run_printcheck(tmp, exe=slicer)
                files += list(PRINTCHECK_FILES)
                if not print_result.ok and not force:
                    raise ChannelsNotPrintable(f"{spec_path}: the sliced plate does not print every channel "
                                               f"(fix the spec or build anyway with --force): "
                                               f"{print_result.failure_text()}")
            if print_note and progress and printed:
                status(f"print check {print_note}")
        with steps.step("preview and tilt plot"):
            picture_times = pictures.collect()
            files += ["preview.png", "tilt_limits.png", "precision.md"]
            files += ["precision.png"] if (tmp / "precision.png").is_file() else []
        with steps.step("fill guide"):
            guide = None
            if printed:
                guide = fill_guide(geometry, cap_dims, vent_grooves=spec.print.printer == "resin")
                files += write_fill_guide(guide, tmp)
        with steps.step("report"):
            files.append("report.md")
            timings = {**steps.timings, **{f"{k} (parallel)": v for k, v in picture_times.items()}}
            print_md = ((tmp / "printcheck.md").read_text(encoding="utf-8") if print_result is not None
                        else f"## Print check (toolpaths)\n\nNot run: {print_note}.\n")
            text = build_report(spec, spec_path, geometry, cap_dims, volumes, checks, feasibility.markdown(),
                                timings, files, (tmp / "precision.md").read_text(encoding="utf-8"), print_md,
                                guide)
            (tmp / "report.md").write_text(text, encoding="utf-8")
        with steps.step("replace export folder"):
            default_permissions(tmp)
            replace_folder(tmp, final)
    except BaseException:
        pictures.close(cancel=True)  # no writes into tmp after this
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        pictures.close()
    timings = {**steps.timings, **{f"{k} (parallel)": v for k, v in picture_times.items()}}  # + last step
    return BuildResult(final.resolve(), checks, timings, feasibility.feasible,
                       wall_s=time.perf_counter() - t_start, files=tuple(files),
                       print_failures=print_result.failure_text() if print_result is not None else "")
