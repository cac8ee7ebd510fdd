"""The human report of a build (``report.md``): dimensions, channels, volumes, filling, checks.

The title, frame F and dimension table come from the design's family
(:meth:`~chic_design.families.base.Family.report_head`); the filling section is the fill guide's
(:func:`~chic_design.report.fill_guide.fill_guide_markdown`); the rest is the same for every family.
"""

from __future__ import annotations

import numpy as np

from chic_design.cad.channels import blank_volume_mm3, channel_volume_mm3
from chic_design.cad.parts import CapDims
from chic_design.families import family_of
from chic_design.feasibility.contacts import touching_channels
from chic_design.report.fill_guide import (
    EXTRA_ML_PER_PORT,
    FillGuide,
    connected_groups,
    fill_guide,
    fill_guide_markdown,
)
from chic_register.model.geometry import FiducialGeometry


def touching_text(geometry: FiducialGeometry) -> str:
    """Which channels meet (near the end faces, typically) and so form connected groups."""
    pairs = touching_channels(geometry)
    if not pairs:
        return "No two channels touch: each fills on its own."
    joined = connected_groups(geometry.ids, [(a, b) for a, b, _, _ in pairs])
    groups = sorted(tuple(sorted(g)) for g in joined if len(g) > 1)
    where = "; ".join(f"{a}-{b} at z {lo:.1f}..{hi:.1f} mm" for a, b, lo, hi in pairs)
    names = "; ".join(", ".join(g) for g in groups)
    return (f"Channels that touch, and are connected there: {where}. Connected groups: {names}. "
            "A group fills as one vessel (its fill and vent ports are under Filling and closing). "
            "Where channels touch, their images merge at those heights.")


def channel_rows(geometry: FiducialGeometry) -> list[dict]:
    """One row per channel: id, role, kind, angle(s), pitch, length (mm), fluid volume (mm^3)."""
    length = geometry.body.length
    rows = []
    for t in geometry.tubes:
        kind, angles, pitch = t.describe()
        rows.append({
            "id": t.id, "role": t.role, "kind": kind, "angle_deg": angles, "pitch": pitch,
            "diameter_mm": t.diameter, "length_mm": t.length_mm,
            "fluid_mm3": channel_volume_mm3(t, 0.0, length),
        })
    return rows


def rod_table(geometry: FiducialGeometry) -> list[str]:
    """The rods of hardware that is not printed here: id, role, kind, angle, diameter, length (no fluid)."""
    out = ["| id | role | kind | angle (deg) | diameter (mm) | centreline length (mm) | from (mm) | to (mm) |",
           "|---|---|---|---|---|---|---|---|"]
    for t in geometry.tubes:
        kind, angles, _ = t.describe()
        a, b = t.points([0.0, 1.0])
        out.append(f"| {t.id} | {t.role} | {kind} | {angles} | {t.diameter:g} | {t.length_mm:.2f} | "
                   f"{', '.join(f'{v:g}' for v in np.round(a, 3))} | {', '.join(f'{v:g}' for v in np.round(b, 3))} |")
    return out


def build_report(spec, spec_path, geometry: FiducialGeometry, cap_dims: CapDims | None,
                 part_volumes_mm3: dict[str, float], verify_result, feasibility_markdown: str | None,
                 timings_s: dict[str, float], files: list[str], precision_markdown: str | None = None,
                 print_markdown: str | None = None, guide: FillGuide | None = None) -> str:
    """The text of ``report.md``; ``cap_dims`` are the caps' dimensions the parts were made with.

    ``guide``: the fill guide written beside the report (made from ``geometry`` and ``cap_dims`` if None).
    ``cap_dims`` None: hardware that is not printed here (no parts, no filling).
    """
    if cap_dims is None:
        return _unprinted_report(spec, spec_path, geometry, verify_result, feasibility_markdown, timings_s, files,
                                 precision_markdown)
    guide = guide if guide is not None else fill_guide(geometry, cap_dims)
    head = family_of(spec).report_head(spec, geometry, cap_dims)
    rows = channel_rows(geometry)
    sum_nominal = sum(r["fluid_mm3"] for r in rows)
    cut = blank_volume_mm3(geometry) - part_volumes_mm3["body"]
    out = [
        f"# {head.title} `{geometry.name}`",
        "",
        f"{spec.description}".strip() or "",
        "",
        f"Built from `{spec_path}` (sha256 `{(geometry.source or {}).get('spec_sha256', '?')[:16]}...`) by "
        f"{(geometry.source or {}).get('generator', 'chic-design')}. All parts are in the fiducial frame F "
        f"({head.frame_text}).",
        "",
        "## Dimensions",
        "",
        "| quantity | value |",
        "|---|---|",
        *head.dimension_rows,
        "",
        "## Channels",
        "",
        "| id | role | kind | angle (deg) | pitch (deg/mm) | diameter (mm) | centreline length (mm) | fluid (mL) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    out += [
        f"| {r['id']} | {r['role']} | {r['kind']} | {r['angle_deg']} | {r['pitch']} | {r['diameter_mm']:g} | "
        f"{r['length_mm']:.2f} | {r['fluid_mm3'] / 1000:.3f} |"
        for r in rows
    ]
    out += [
        "",
        f"Fluid to fill: {sum_nominal / 1000:.3f} mL summed over the channels (pi r^2 x centreline length); "
        f"the CAD body has {cut / 1000:.3f} mL of channel space (solid frame minus body)"
        + (f": channels that touch near the end faces share {max(sum_nominal - cut, 0.0):.1f} mm^3."
           if sum_nominal - cut > 0.5 else "."),
        f"The fluid per group of connected channels, to draw with {EXTRA_ML_PER_PORT:g} mL extra per port for the "
        "needle and the ports, is under Filling and closing.",
        "",
        touching_text(geometry),
        "",
        "## Parts",
        "",
        "| part | volume (mm^3) | files |",
        "|---|---|---|",
    ]
    out += [
        f"| {name} | {vol:.1f} | `{name}.stl`, `{name}.step`, `{name}.3mf` |"
        for name, vol in part_volumes_mm3.items()
    ]
    out += [
        "",
        "`assembly.step` holds the three labelled parts in their assembled positions; "
        "`geometry.yaml` is what the registration solver reads; `preview.png` shows the channels; "
        "`feasibility.json` is the feasibility report (as `chic-design check --json`); `fill_guide.pdf` "
        "(or `fill_guide.html`) is the fill and seal guide to take to the bench.",
        "",
        "![preview](preview.png)",
        "",
        fill_guide_markdown(guide),
        feasibility_markdown.strip() if feasibility_markdown else "## Feasibility\n\n(not checked)",
        "",
        *([precision_markdown.strip(), ""] if precision_markdown else []),
        "## Output checks",
        "",
        "Body sections checked at z = "
        + ", ".join(f"{z:.2f}" for z in verify_result.section_heights_mm)
        + " mm (heights where no two channels touch).",
        "",
        verify_result.markdown(),
        "",
        *([print_markdown.strip(), ""] if print_markdown else []),
    ]
    return "\n".join(out + build_section(timings_s, files))


def _unprinted_report(spec, spec_path, geometry: FiducialGeometry, verify_result, feasibility_markdown: str | None,
                      timings_s: dict[str, float], files: list[str], precision_markdown: str | None) -> str:
    """``report.md`` of hardware described for the solver only: dimensions, rods, coordinates, feasibility."""
    head = family_of(spec).report_head(spec, geometry, None)
    src = geometry.source or {}
    out = [
        f"# {head.title} `{geometry.name}`",
        "",
        f"{spec.description}".strip() or "",
        "",
        f"Built from `{spec_path}` (sha256 `{src.get('spec_sha256', '?')[:16]}...`) by "
        f"{src.get('generator', 'chic-design')}. Coordinates are in the fiducial frame F ({head.frame_text}).",
        "",
        "Commercial hardware: nothing is printed. `geometry.yaml` describes its rods for the registration "
        "solver; there are no part files, print plate or fill guide.",
        "",
        "## Dimensions",
        "",
        "| quantity | value |",
        "|---|---|",
        *head.dimension_rows,
        "",
        "## Rods",
        "",
        *rod_table(geometry),
        "",
    ]
    fc = geometry.frame_coordinates
    if fc is not None:
        T = fc.T_frame_from_fiducial
        out += ["## Frame coordinates", "", f"System `{fc.system}`: {fc.axes}.", "",
                "T_frame_from_fiducial (F to the frame's coordinates, mm):", "", "```",
                *("[" + ", ".join(f"{v:g}" for v in row) + "]" for row in T), "```", ""]
        if fc.reference:
            out += [f"Source: {fc.reference}.", ""]
    out += [
        "`geometry.yaml` is what the registration solver reads; `preview.png` shows the rods; "
        "`feasibility.json` is the feasibility report (as `chic-design check --json`).",
        "",
        "![preview](preview.png)",
        "",
        feasibility_markdown.strip() if feasibility_markdown else "## Feasibility\n\n(not checked)",
        "",
        *([precision_markdown.strip(), ""] if precision_markdown else []),
        "## Output checks",
        "",
        verify_result.markdown(),
        "",
    ]
    return "\n".join(out + build_section(timings_s, files))


def build_section(timings_s: dict, files) -> list[str]:
    """The report's closing lines: each build step's seconds and the files written."""
    return (["## Build", "", "| step | seconds |", "|---|---|"]
            + [f"| {k} | {v:.2f} |" for k, v in timings_s.items()]
            + ["", "Files: " + ", ".join(f"`{f}`" for f in files), ""])
