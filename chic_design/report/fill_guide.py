"""The fill and seal guide for the bench: which port fills which channels, in what order, and how much fluid.

From the geometry objects and the cap dimensions alone (no CAD kernel):

- the top cap's fill ports (:func:`~chic_design.cad.channels.fill_ports_xy`), numbered 1..n in tube order;
  channels that end at the same point share a port;
- the groups of channels that form one vessel: channels whose openings coincide at an end face (at the top
  they share a port; at the bottom the cap's plate closes one opening over both) or that touch in the wall
  (:func:`~chic_design.feasibility.contacts.touching_channels`);
- per group the port to inject through, the ports that vent, its nominal fluid volume, and the order to seal.

:func:`fill_guide` makes the :class:`FillGuide` record; :func:`write_fill_guide` writes ``fill_guide.png``
(the top cap seen from above), ``fill_guide.html`` (self-contained) and ``fill_guide.pdf`` (A4, to print);
:func:`fill_guide_markdown` is the section of ``report.md``.
"""

from __future__ import annotations

import base64
import html
import io
import re
import textwrap
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from chic_design.cad.channels import channel_openings_xy, channel_volume_mm3, fill_ports_xy
from chic_design.feasibility.contacts import touching_channels
from chic_register.model.body import Body
from chic_register.model.geometry import FiducialGeometry
from chic_register.util.atomic import atomic_path, write_bytes, write_text

if TYPE_CHECKING:  # the type only: importing chic_design.cad.parts loads the CAD kernel
    from chic_design.cad.parts import CapDims

#: The files :func:`write_fill_guide` writes, in order.
FILL_GUIDE_FILES = ("fill_guide.png", "fill_guide.html", "fill_guide.pdf")

#: Two openings closer than this (mm) are one opening (as :func:`~chic_design.cad.channels.distinct_points`).
SAME_POINT_MM = 1e-6

#: Blunt dispensing needles: gauge and outside diameter (mm), thickest first.
NEEDLE_GAUGES_MM = ((18, 1.27), (20, 0.91), (21, 0.82), (22, 0.72), (23, 0.64), (25, 0.51), (27, 0.41),
                    (30, 0.31), (32, 0.24))

#: The needle's outside diameter at most this share of the port's, so air can leave around it.
NEEDLE_PORT_SHARE = 0.5

#: Extra fluid to draw per port (mL): what the needle, the port and the topping-up take.
EXTRA_ML_PER_PORT = 0.1

#: A4 portrait (inches), for the PDF.
A4_IN = (8.27, 11.69)


@dataclass(frozen=True)
class FillPort:
    """A fill port of the top cap: ``number`` (1..n), centre (mm, frame F) and the channels it opens onto."""

    number: int
    x_mm: float
    y_mm: float
    channel_ids: tuple[str, ...]


@dataclass(frozen=True)
class ChannelGroup:
    """Channels that are connected and so fill as one vessel.

    ``volume_mm3`` is nominal: the channels' volumes summed (pi r^2 x centreline length), overlaps where
    channels meet not subtracted. ``fill_port`` is the port to inject through, ``vent_ports`` the other
    ports of the group, which let the air out; ``joints`` says where its channels connect.
    """

    number: int
    channel_ids: tuple[str, ...]
    port_numbers: tuple[int, ...]
    volume_mm3: float
    fill_port: int
    vent_ports: tuple[int, ...]
    joints: tuple[str, ...] = ()

    @property
    def volume_ml(self) -> float:
        return self.volume_mm3 / 1000.0

    @property
    def draw_ml(self) -> float:
        """Fluid to draw into the syringe (mL): the volume plus :data:`EXTRA_ML_PER_PORT` per port."""
        return self.volume_ml + EXTRA_ML_PER_PORT * len(self.port_numbers)


@dataclass(frozen=True)
class FillGuide:
    """How to fill and seal one fiducial: its ports, channel groups, the sealing order and the steps.

    ``cap_outline_mm``: the top cap's outside, a radius (annulus) or a half side (square), mm;
    ``openings_xy_mm``: each channel's opening in the top face, ``{id: (x, y)}``;
    ``channel_diameters_mm``: ``{id: diameter}``; ``seal_order``: port numbers, first sealed first.
    ``needle_gauge`` and ``needle_od_mm``: a blunt needle thin enough for the ports (None when the cap
    has no ports: the channels are then filled before the top cap goes on).
    """

    name: str
    body: Body
    port_diameter_mm: float
    port_depth_mm: float
    clearance_mm: float
    cap_outline_mm: float
    ports: tuple[FillPort, ...]
    groups: tuple[ChannelGroup, ...]
    seal_order: tuple[int, ...]
    openings_xy_mm: dict
    channel_diameters_mm: dict
    needle_gauge: int | None
    needle_od_mm: float | None
    procedure: tuple[str, ...] = ()
    bubble_check: tuple[str, ...] = ()
    vent_grooves: bool = False

    @property
    def has_ports(self) -> bool:
        return self.port_diameter_mm > 0 and bool(self.ports)

    @property
    def total_volume_mm3(self) -> float:
        return sum(g.volume_mm3 for g in self.groups)

    def group_of_port(self, number: int) -> ChannelGroup:
        return next(g for g in self.groups if number in g.port_numbers)


def same_point(a, b) -> bool:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b))) <= SAME_POINT_MM


def connected_groups(ids, pairs) -> list[tuple[str, ...]]:
    """Union-find over ``ids`` joined by ``pairs`` ``[(a, b)]``: the groups, each in ``ids`` order, by first member."""
    parent = {i: i for i in ids}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in pairs:
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb, key=list(ids).index)] = min(ra, rb, key=list(ids).index)
    groups: dict[str, list[str]] = {}
    for i in ids:
        groups.setdefault(root(i), []).append(i)
    return [tuple(g) for g in groups.values()]


def needle_for(port_diameter_mm: float) -> tuple[int, float] | None:
    """The thickest blunt needle (gauge, outside diameter mm) that leaves room for air in the port."""
    fits = [(g, od) for g, od in NEEDLE_GAUGES_MM if od <= NEEDLE_PORT_SHARE * port_diameter_mm]
    return fits[0] if fits else None


def fmt_xy(p) -> str:
    return f"({float(p[0]):.1f}, {float(p[1]):.1f})"


def fill_guide(geometry: FiducialGeometry, cap_dims: CapDims, vent_grooves: bool = False) -> FillGuide:
    """The fill guide of ``geometry`` with caps of ``cap_dims`` (a :class:`~chic_design.cad.parts.CapDims`);
    ``vent_grooves``: the body has a resin print's vent grooves in its lower end face, which the glue must fill.

    Ports are numbered in tube order. A group is injected through the port whose channel reaches the bottom
    first (the shortest channel), preferring a port over one channel (the fluid then runs one way) and then
    the lowest number; the rest vent. Groups are sealed in fill order, in each its vents first and its fill
    port last, topped up just before.
    """
    length = geometry.body.length
    ids = list(geometry.ids)
    tubes = {t.id: t for t in geometry.tubes}
    top = channel_openings_xy(geometry, length)
    bottom = channel_openings_xy(geometry, 0.0)
    ports = tuple(
        FillPort(k, float(p[0]), float(p[1]), tuple(i for i in ids if same_point(top[i], p)))
        for k, p in enumerate(fill_ports_xy(geometry), start=1)
    )
    pairs, joints = [], []
    for port in ports:
        for a, b in zip(port.channel_ids, port.channel_ids[1:]):
            pairs.append((a, b))
            joints.append((a, f"{a} and {b}: one opening at the top, under port {port.number}"))
    for j, a in enumerate(ids):
        for b in ids[j + 1:]:
            if same_point(bottom[a], bottom[b]):
                pairs.append((a, b))
                joints.append((a, f"{a} and {b}: one opening at the bottom, at {fmt_xy(bottom[a])} mm"))
    for a, b, lo, hi in touching_channels(geometry):
        if (a, b) in pairs or (b, a) in pairs:  # they meet where they share an opening: said already
            continue
        pairs.append((a, b))
        joints.append((a, f"{a} and {b}: touch in the wall at z {lo:.1f}..{hi:.1f} mm"))
    groups = []
    for n, members in enumerate(connected_groups(ids, pairs), start=1):
        mine = [p for p in ports if set(p.channel_ids) & set(members)]
        fill = min(mine, key=lambda p: (min(tubes[i].length_mm for i in p.channel_ids), len(p.channel_ids),
                                        p.number)) if mine else None
        groups.append(ChannelGroup(
            number=n, channel_ids=members, port_numbers=tuple(p.number for p in mine),
            volume_mm3=float(sum(channel_volume_mm3(tubes[i], 0.0, length) for i in members)),
            fill_port=fill.number if fill else 0,
            vent_ports=tuple(p.number for p in mine if p is not fill),
            joints=tuple(text for a, text in joints if a in members),
        ))
    seal = tuple(k for g in groups for k in (*g.vent_ports, g.fill_port) if k)
    needle = needle_for(cap_dims.port_diameter) if cap_dims.port_diameter > 0 else None
    b = geometry.body
    body_outline = float(max(b.outer_half_mm)) if b.outer_half_mm is not None else b.outer_diameter / 2
    guide = FillGuide(
        name=geometry.name, body=b, port_diameter_mm=float(cap_dims.port_diameter),
        port_depth_mm=float(cap_dims.thickness), clearance_mm=float(cap_dims.clearance),
        cap_outline_mm=float(body_outline + cap_dims.clearance + cap_dims.skirt_wall),
        ports=ports, groups=tuple(groups), seal_order=seal,
        openings_xy_mm={i: (float(top[i][0]), float(top[i][1])) for i in ids},
        channel_diameters_mm={i: float(tubes[i].diameter) for i in ids},
        needle_gauge=needle[0] if needle else None, needle_od_mm=needle[1] if needle else None,
        vent_grooves=vent_grooves,
    )
    return replace(guide, procedure=procedure_steps(guide), bubble_check=bubble_check_steps())


def group_line(guide: FillGuide, g: ChannelGroup) -> str:
    """One group's filling instruction (markdown), starting with the group."""
    what = f"group {g.number} ({', '.join(g.channel_ids)}; {g.volume_ml:.2f} mL, draw {g.draw_ml:.2f} mL)"
    slowly = "Push slowly, so the fluid runs down and the air rises out"
    if not guide.has_ports:
        return f"{what}: fill each of its channels through its opening in the top face. {slowly}."
    if not g.vent_ports:
        return f"{what}: inject through port {g.fill_port}. {slowly} around the needle."
    vents = ", ".join(str(k) for k in g.vent_ports)
    return (f"{what}: inject through port {g.fill_port}; port{'s' if len(g.vent_ports) > 1 else ''} {vents} "
            f"vent{'' if len(g.vent_ports) > 1 else 's'}. {slowly} through the vents. "
            "Stop when fluid stands in every port of the group.")


def procedure_steps(guide: FillGuide) -> tuple[str, ...]:
    """The steps at the bench, in order (markdown: `code`, **bold**)."""
    sizes = sorted(set(guide.channel_diameters_mm.values()))
    wire = f"the {sizes[0]:g} mm channels" if len(sizes) == 1 else f"the channels (narrowest {sizes[0]:g} mm)"
    steps = [
        "Print the body and both caps: open `plate.3mf` in PrusaSlicer, where they lie in their print "
        "orientation (the body on an end face, both caps plate down) with the settings the channels need; "
        "choose your printer and material and keep those settings. (The STL files are in frame F, in their "
        "assembled positions.)",
        f"Clear every channel with a wire slightly thinner than {wire} and check that "
        "light shows through each one, end to end. Blow out the dust.",
        "Glue the **bottom cap** (`cap_bottom`) onto the body: a thin bead of epoxy (or cyanoacrylate for "
        "resins that tolerate it) on the lower end face and inside the skirt, then slide it on. The skirt is a "
        f"slip fit with {guide.clearance_mm:g} mm radial clearance; the plate seals every channel opening at "
        "z = 0. Let it cure.",
    ]
    if guide.vent_grooves:
        steps[-1] = steps[-1].replace(" Let it cure.", " Work the glue into the vent grooves in the lower end "
                                      "face (one from each channel to the outside, for the resin print): "
                                      "filled, they seal. Let it cure.")
    if guide.has_ports:
        steps.append(
            "Glue the **top cap** (`cap_top`) the same way, turned so that every fill port sits over its channel "
            "opening as in `fill_guide.png` (check by looking through the ports). Keep glue away from the ports. "
            "Let it cure.")
        steps.append(
            "Stand the fiducial upright, top cap up. Fill a syringe with the MRI contrast fluid or gel of your "
            f"protocol (for example diluted gadolinium, or a saline/agarose gel) and fit a blunt needle thinner "
            f"than the {guide.port_diameter_mm:g} mm ports"
            + (f" ({guide.needle_gauge} G, {guide.needle_od_mm:g} mm)" if guide.needle_gauge else "")
            + ". Push the needle just into the port.")
    else:
        steps.append(
            "The top cap has no ports: fill before it goes on. Stand the body upright, bottom cap down, and fill "
            "with the MRI contrast fluid or gel of your protocol (for example diluted gadolinium, or a "
            "saline/agarose gel) from a syringe with a blunt needle thinner than the channels.")
    for g in guide.groups:  # one step per group: slowly, so the fluid runs down and the air rises out
        steps.append(f"Fill {group_line(guide, g)}")
    steps.append("Tap the body on the bench and flick it to bring bubbles up; wait a minute and tap again. "
                 "Top up every port to a small meniscus.")
    if guide.has_ports:
        order = ", ".join(str(k) for k in guide.seal_order)
        steps.append(
            f"Seal the ports in this order: {order} (in each group the vents first, its fill port last, topped up "
            "just before). A drop of UV-curing resin or epoxy over each port; cure it before moving the fiducial.")
    else:
        steps.append("Glue the **top cap** (`cap_top`) on, with the channels full to a small meniscus, and let it "
                     "cure upright.")
    return tuple(steps)


def bubble_check_steps() -> tuple[str, ...]:
    """How to find an air bubble in the first scan."""
    return (
        "Scan the filled fiducial once before it is used. Air gives no signal.",
        "Along a channel (a reformat or a slice along the axis) a filled channel is a bright line: a dark gap "
        "in it is a bubble.",
        "On axial slices every channel is a bright dot in every slice: a channel missing from some slices has "
        "a bubble there.",
        "`chic-register solve` with `--json` lists per slice the tubes it could not find (`missing_tubes`): "
        "the same tube missing in neighbouring slices points to a bubble at that depth.",
        "To mend it: remove the seal over a port of that group, hold the fiducial so that this port is highest, "
        "tap until the bubble comes out, top up and seal again.",
    )


# --- the picture -----------------------------------------------------------------------------------------


def group_colours(guide: FillGuide) -> dict[int, tuple]:
    """One colour per group number (matplotlib's tab10)."""
    import matplotlib  # deferred: matplotlib loads only when a picture is drawn

    cmap = matplotlib.colormaps["tab10"]
    return {g.number: cmap((g.number - 1) % 10) for g in guide.groups}


def draw_top_cap(ax, guide: FillGuide) -> None:
    """The top cap seen from above (x right, y up in F): outline, bore, channel openings, numbered ports."""
    from matplotlib.patches import Circle, Patch, Rectangle  # deferred: matplotlib loads only when drawing

    b, r = guide.body, guide.cap_outline_mm
    if b.outer_half_mm is not None:  # square or rectangular frame: the cap is its outside grown by the skirt
        (ox, oy), (ix, iy) = b.outer_half_mm, b.inner_half_mm
        grow = r - max(ox, oy)
        cx, cy = ox + grow, oy + grow
        ax.add_patch(Rectangle((-cx, -cy), 2 * cx, 2 * cy, fc="0.92", ec="0.3", lw=1.2))
        ax.add_patch(Rectangle((-ix, -iy), 2 * ix, 2 * iy, fc="white", ec="0.3", lw=1.2))
        ax.add_patch(Rectangle((-ox, -oy), 2 * ox, 2 * oy, fc="none", ec="0.6", lw=0.8, ls="--"))
    else:
        ax.add_patch(Circle((0, 0), r, fc="0.92", ec="0.3", lw=1.2))
        ax.add_patch(Circle((0, 0), b.inner_diameter / 2, fc="white", ec="0.3", lw=1.2))
        ax.add_patch(Circle((0, 0), b.outer_diameter / 2, fc="none", ec="0.6", lw=0.8, ls="--"))
    colours = group_colours(guide)
    group_of = {i: g.number for g in guide.groups for i in g.channel_ids}
    for tid, (x, y) in guide.openings_xy_mm.items():
        ax.add_patch(Circle((x, y), guide.channel_diameters_mm[tid] / 2, fc="none", ec=colours[group_of[tid]],
                            lw=1.0, ls=":"))
    handles = []
    for p in guide.ports:
        g = guide.group_of_port(p.number)
        c = colours[g.number]
        d = guide.port_diameter_mm if guide.has_ports else guide.channel_diameters_mm[p.channel_ids[0]]
        fill = p.number == g.fill_port
        ax.add_patch(Circle((p.x_mm, p.y_mm), d / 2, fc=c, ec="black", lw=1.6 if fill else 0.8))
        out = np.array([p.x_mm, p.y_mm])
        out = out / (np.linalg.norm(out) or 1.0)
        lx, ly = np.array([p.x_mm, p.y_mm]) + out * (0.09 * r + d)
        ax.text(lx, ly, str(p.number), ha="center", va="center", fontsize=10, fontweight="bold", color=c,
                bbox={"boxstyle": "circle,pad=0.15", "fc": "white", "ec": c, "lw": 1.0})
        role = "fill" if fill else "vent"
        handles.append(Patch(fc=c, ec="black",
                             label=f"{p.number}: {', '.join(p.channel_ids)}  (group {g.number}, {role})"))
    ax.set_xlim(-1.25 * r, 1.25 * r)
    ax.set_ylim(-1.25 * r, 1.25 * r)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.annotate("", xy=(-1.05 * r + 0.25 * r, -1.15 * r), xytext=(-1.05 * r, -1.15 * r),
                arrowprops={"arrowstyle": "->", "lw": 1.2})
    ax.annotate("", xy=(-1.05 * r, -1.15 * r + 0.25 * r), xytext=(-1.05 * r, -1.15 * r),
                arrowprops={"arrowstyle": "->", "lw": 1.2})
    ax.text(-1.05 * r + 0.28 * r, -1.15 * r, "x", va="center", fontsize=9)
    ax.text(-1.05 * r, -1.15 * r + 0.28 * r, "y", ha="center", fontsize=9)
    what = "fill ports" if guide.has_ports else "channel openings (no ports: fill before capping)"
    ax.set_title(f"{guide.name}: top cap seen from above, {what}", fontsize=10)
    ports_legend = ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8,
                             frameon=False, title="port: channels", title_fontsize=9, alignment="left")
    ax.add_artist(ports_legend)
    groups = [Patch(fc=colours[g.number], ec="black",
                    label=f"group {g.number}: {g.volume_ml:.2f} mL, fill through {g.fill_port or '-'}")
              for g in guide.groups]
    ax.legend(handles=groups, loc="lower left", bbox_to_anchor=(1.02, 0.0), fontsize=8, frameon=False,
              title="channel groups (nominal fluid)", title_fontsize=9, alignment="left")


def picture_png(guide: FillGuide, dpi: int = 130) -> bytes:
    """``fill_guide.png`` as bytes (Agg backend)."""
    from matplotlib.figure import Figure  # deferred: matplotlib loads only when drawing (no pyplot: Agg, no GUI)

    fig = Figure(figsize=(9.0, 5.6))
    ax = fig.add_axes((0.08, 0.09, 0.52, 0.84))
    draw_top_cap(ax, guide)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


# --- the files -------------------------------------------------------------------------------------------


def port_rows(guide: FillGuide) -> list[tuple[str, ...]]:
    """Rows of the ports table: port, x (mm), y (mm), channels, group, role."""
    rows = []
    for p in guide.ports:
        g = guide.group_of_port(p.number)
        rows.append((str(p.number), f"{p.x_mm:.2f}", f"{p.y_mm:.2f}", ", ".join(p.channel_ids), str(g.number),
                     "fill" if p.number == g.fill_port else "vent"))
    return rows


def group_rows(guide: FillGuide) -> list[tuple[str, ...]]:
    """Rows of the groups table: group, channels, ports, fill through, vents, fluid (mL), draw (mL)."""
    return [(str(g.number), ", ".join(g.channel_ids), ", ".join(map(str, g.port_numbers)) or "-",
             str(g.fill_port) if g.fill_port else "-", ", ".join(map(str, g.vent_ports)) or "-",
             f"{g.volume_ml:.3f}", f"{g.draw_ml:.2f}") for g in guide.groups]


PORT_HEAD = ("port", "x (mm)", "y (mm)", "channels", "group", "role")
GROUP_HEAD = ("group", "channels", "ports", "fill through", "vents", "fluid (mL)", "draw (mL)")


def volume_note(guide: FillGuide) -> str:
    return (f"Fluid in all: {guide.total_volume_mm3 / 1000:.3f} mL. Volumes are nominal: each channel's "
            "pi r^2 x centreline length, summed; where channels meet the overlap is not subtracted. "
            f"Draw {EXTRA_ML_PER_PORT:g} mL extra per port for the needle, the port and the topping up.")


def md_table(head, rows) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *("| " + " | ".join(r) + " |" for r in rows)]


def fill_guide_markdown(guide: FillGuide) -> str:
    """The ``## Filling and closing`` section of ``report.md``: ports, groups and volumes, steps, bubble check."""
    out = [
        "## Filling and closing",
        "",
        "To take to the bench: [fill_guide.pdf](fill_guide.pdf) (A4, to print), "
        "[fill_guide.html](fill_guide.html) (one file, picture included), [fill_guide.png](fill_guide.png).",
        "",
        "![fill ports, top cap seen from above](fill_guide.png)",
        "",
        f"Fill ports of the top cap ({guide.port_diameter_mm:g} mm, through the {guide.port_depth_mm:g} mm plate; "
        "x, y in frame F, seen from above):" if guide.has_ports else
        "The top cap has no fill ports: the channels are filled through their openings before it goes on.",
        "",
        *md_table(PORT_HEAD, port_rows(guide)),
        "",
        "Channel groups (channels that are connected fill as one vessel):",
        "",
        *md_table(GROUP_HEAD, group_rows(guide)),
        "",
        volume_note(guide),
        "",
    ]
    joined = [g for g in guide.groups if g.joints]
    if joined:
        out += ["Where the channels of a group connect:", ""]
        out += [f"- group {g.number}: " + "; ".join(g.joints) for g in joined]
        out += [""]
    out += [f"{k}. {s}" for k, s in enumerate(guide.procedure, start=1)]
    out += ["", "Checking for bubbles in the first scan:", ""]
    out += [f"- {s}" for s in guide.bubble_check]
    return "\n".join(out) + "\n"


def html_inline(text: str) -> str:
    """Markdown `code` and **bold** of one step as HTML (escaped)."""
    text = html.escape(text)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", text)


def plain(text: str) -> str:
    """A step without its markdown marks, for the PDF."""
    return text.replace("**", "").replace("`", "")


def html_table(head, rows) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    trs = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{trs}</table>"


def guide_html(guide: FillGuide, png: bytes) -> str:
    """``fill_guide.html``: one file, the picture embedded (base64), the tables and the steps."""
    joints = "".join(f"<li>group {g.number}: {html.escape('; '.join(g.joints))}</li>" for g in guide.groups
                     if g.joints)
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>Fill guide: {html.escape(guide.name)}</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:1em auto;padding:0 1em;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #999;padding:0.2em 0.6em;"
        "text-align:left}th{background:#eee}img{max-width:100%}code{background:#f3f3f3;padding:0 0.2em}"
        "@media print{body{max-width:none}}</style>",
        "</head><body>",
        f"<h1>Fill and seal guide: {html.escape(guide.name)}</h1>",
        f'<img alt="top cap seen from above, ports numbered" src="data:image/png;base64,'
        f'{base64.b64encode(png).decode("ascii")}">',
        "<h2>Fill ports</h2>",
        html_table(PORT_HEAD, port_rows(guide)),
        "<h2>Channel groups</h2>",
        html_table(GROUP_HEAD, group_rows(guide)),
        f"<p>{html.escape(volume_note(guide))}</p>",
        f"<ul>{joints}</ul>" if joints else "",
        "<h2>Procedure</h2>",
        "<ol>" + "".join(f"<li>{html_inline(s)}</li>" for s in guide.procedure) + "</ol>",
        "<h2>Checking for bubbles in the first scan</h2>",
        "<ul>" + "".join(f"<li>{html_inline(s)}</li>" for s in guide.bubble_check) + "</ul>",
        "</body></html>",
        "",
    ])


def text_table(head, rows) -> list[str]:
    """A fixed-width table for the PDF."""
    widths = [max(len(h), *(len(r[k]) for r in rows)) if rows else len(h) for k, h in enumerate(head)]
    line = "  ".join(h.ljust(w) for h, w in zip(head, widths))
    return [line, "-" * len(line), *("  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows)]


def pdf_pages(guide: FillGuide) -> list:
    """The PDF's A4 pages as matplotlib figures: the picture and tables, then the steps."""
    from matplotlib.figure import Figure  # deferred: matplotlib loads only when drawing (no pyplot: Agg, no GUI)

    first = Figure(figsize=A4_IN)
    first.text(0.07, 0.96, f"Fill and seal guide: {guide.name}", fontsize=15, fontweight="bold", va="top")
    ax = first.add_axes((0.09, 0.50, 0.50, 0.40))
    draw_top_cap(ax, guide)
    ax.set_title("top cap seen from above", fontsize=9)
    lines = ["Fill ports", *text_table(PORT_HEAD, port_rows(guide)), "", "Channel groups",
             *text_table(GROUP_HEAD, group_rows(guide)), "", *textwrap.wrap(volume_note(guide), 95)]
    for g in guide.groups:
        if g.joints:
            lines += textwrap.wrap(f"Group {g.number} connects: " + "; ".join(g.joints), 95)
    first.text(0.07, 0.44, "\n".join(lines), fontsize=7.5, family="monospace", va="top")
    second = Figure(figsize=A4_IN)
    body = ["Procedure", ""]
    for k, s in enumerate(guide.procedure, start=1):
        body += textwrap.wrap(plain(s), 92, initial_indent=f"{k}. ", subsequent_indent="   ") + [""]
    body += ["Checking for bubbles in the first scan", ""]
    for s in guide.bubble_check:
        body += textwrap.wrap(plain(s), 92, initial_indent="- ", subsequent_indent="  ")
    second.text(0.07, 0.95, "\n".join(body), fontsize=8.5, va="top", linespacing=1.35)
    return [first, second]


def write_fill_guide(guide: FillGuide, folder) -> list[str]:
    """Write :data:`FILL_GUIDE_FILES` into ``folder`` (each atomically); returns their names."""
    from matplotlib.backends.backend_pdf import PdfPages  # deferred: matplotlib loads only when writing

    folder = Path(folder)
    png = picture_png(guide)
    write_bytes(folder / "fill_guide.png", png)
    write_text(folder / "fill_guide.html", guide_html(guide, png))
    with atomic_path(folder / "fill_guide.pdf") as tmp:
        with PdfPages(tmp, metadata={"Title": f"Fill guide: {guide.name}", "Creator": "chic-design",
                                     "CreationDate": None}) as pdf:
            for fig in pdf_pages(guide):
                pdf.savefig(fig)
    return list(FILL_GUIDE_FILES)
