"""Rules a design must meet for ``build`` to make and check it: caps, output checks, useful depth encoding.

``chic-design check`` and ``chic-design build`` must agree: a design that
``check`` calls feasible always builds. :func:`feasibility.check_design`
adds the findings of :func:`build_violations` to its violations, and
``build`` refuses every one of them even with ``--force`` (each makes the
build fail or its output useless):

- ``caps_meet``: the two caps' skirts would reach each other along the body
  (``2 * caps.skirt_height >= body.length``);
- ``cap_wall_too_thin``: the cap plate (``caps.thickness``) or the skirt
  (``caps.skirt_wall``) is thinner than ``print.min_wall``, the same rule as
  the body's walls;
- ``no_clear_section``: no height of the body where every channel is at least
  :data:`~chic_design.verify.SECTION_MARGIN_MM` from the others and from the
  walls, so the build's own section check of ``body.stl`` cannot run;
- ``depth_imprecise``: the helices turn so little that the expected depth
  precision (the feasibility report's centroid-quantisation bound, at the
  protocol's pixel or :data:`IDEAL_PIXEL_MM` for an ideal one) is worse than
  :data:`MAX_DEPTH_SIGMA_MM`: such a design "registers" with a useless depth.
"""

from __future__ import annotations

from chic_register.geometry import FiducialGeometry

from .spec import Spec

#: Worst acceptable 1-sigma depth precision (mm) from the quantisation bound; the repository's designs
#: reach 0.27 (neuro) and 0.32 (needle guide). Noise and tilt only make it worse.
MAX_DEPTH_SIGMA_MM = 1.0
#: Pixel size (mm) at which an "ideal" protocol (pixel_size 0) is judged: the paper's 0.5 mm.
IDEAL_PIXEL_MM = 0.5
#: The codes of this module: ``build`` refuses them even with ``--force``.
HARD_CODES = frozenset({"caps_meet", "cap_wall_too_thin", "no_clear_section", "depth_imprecise"})


def build_violations(spec: Spec, geom: FiducialGeometry, pixel_size_mm: float):
    """Findings (``feasibility.Finding``) that would make ``build`` fail or its output useless."""
    from .feasibility import Finding, depth_sensitivity
    from .verify import SECTION_MARGIN_MM, section_heights

    out = []
    caps, wall, length = spec.caps, spec.print.min_wall, geom.body.length
    key = "frame.height" if getattr(spec, "family", "chic") == "zframe" else "body.length"
    if 2 * caps.skirt_height >= length:
        out.append(Finding("caps_meet", f"caps.skirt_height ({caps.skirt_height:g} mm) must be less than half "
                           f"of {key} ({length:g} mm): the two caps' skirts would meet",
                           "caps.skirt_height"))
    for key, value in (("thickness", caps.thickness), ("skirt_wall", caps.skirt_wall)):
        if value < wall:
            out.append(Finding("cap_wall_too_thin", f"caps.{key} ({value:g} mm) is thinner than print.min_wall "
                               f"({wall:g} mm)", f"caps.{key}"))
    if section_heights(geom).size == 0:
        out.append(Finding("no_clear_section", "no height of the body where every channel is at least "
                           f"{SECTION_MARGIN_MM:g} mm from the others and from the bore and outside: the "
                           "build's section check of body.stl cannot run; widen the wall or thin the channels",
                           "all depths"))
    pixel = pixel_size_mm if pixel_size_mm > 0 else IDEAL_PIXEL_MM
    sigma = depth_sensitivity(geom, pixel).combined_sigma_z_mm
    if sigma is not None and sigma > MAX_DEPTH_SIGMA_MM:
        out.append(Finding("depth_imprecise", f"the helices turn too little: expected depth precision "
                           f"{sigma:.3g} mm at {pixel:g} mm pixels (allowed at most {MAX_DEPTH_SIGMA_MM:g} mm); "
                           "lower helix.offset_deg or raise |helix.pitch_deg_per_mm|", "helix"))
    return out
