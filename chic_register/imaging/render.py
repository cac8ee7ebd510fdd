"""Partial-volume rendering of tube sections: the fluid fraction of each pixel of a slice.

The image of a slice is the fluid fraction of each voxel: the share of the
pixel's area, averaged over the slice thickness, that lies inside a tube
(a point within ``diameter / 2`` of a tube centreline, inside the tube's
extent). It is rendered tube crossing by tube crossing, only in a bounding box
around each crossing:

- the slice thickness is sampled by ``thickness_samples`` sub-planes;
- in each sub-plane, every crossing of a tube centreline is found exactly
  (``section_params`` of the tube objects) and each pixel is
  ``supersample x supersample`` sampled; a sample's distance to the centreline
  is measured to the tangent line at the nearest centreline point (one exact
  re-projection for curved tubes), and its coverage is a linear ramp across the
  sample's footprint, so edges are anti-aliased and blob centroids are
  unbiased to a few thousandths of a pixel.

Pixel (row i, col j) has its centre at slice-frame coordinates
``x = (j - cc) * col_spacing``, ``y = (i - rc) * row_spacing`` with
``(rc, cc) = center_px``; the slice frame S is given by ``T_F_from_S``
(see :func:`chic_register.model.pose.slice_frame`). Used by the simulator
(:mod:`chic_register.imaging.simulate`, which re-exports :func:`render_tubes` and
:func:`render_slice`), the solver and the pose checks (:mod:`chic_register.verify.pixels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import helix_points, helix_tangents


def sample_offsets(n: int) -> np.ndarray:
    """Sub-sample centres within a unit pixel, relative to its centre; shape (n,)."""
    return (np.arange(n) + 0.5) / n - 0.5


def _plane_offsets_mm(thickness_mm: float, n: int) -> np.ndarray:
    """Midpoint-rule sub-plane offsets along the slice normal; shape (K,)."""
    if thickness_mm <= 0 or n <= 1:
        return np.zeros(1)
    return sample_offsets(n) * thickness_mm


@dataclass(frozen=True)
class _Grid:
    """Pixel grid of the image in the slice frame."""

    shape: tuple[int, int]
    spacing: tuple[float, float]  # (row, col) mm
    center: tuple[float, float]  # (rc, cc) pixel coordinates of the S origin
    sub: np.ndarray  # (s,) sub-sample offsets in pixels

    def box(self, x_mm: float, y_mm: float, hx_mm: float, hy_mm: float):
        """Pixel index ranges (i0, i1, j0, j1) (inclusive) covering a rectangle, clipped; None if empty."""
        rs, cs = self.spacing
        rc, cc = self.center
        j0 = max(0, int(math.floor((x_mm - hx_mm) / cs + cc)) - 1)
        j1 = min(self.shape[1] - 1, int(math.ceil((x_mm + hx_mm) / cs + cc)) + 1)
        i0 = max(0, int(math.floor((y_mm - hy_mm) / rs + rc)) - 1)
        i1 = min(self.shape[0] - 1, int(math.ceil((y_mm + hy_mm) / rs + rc)) + 1)
        if j0 > j1 or i0 > i1:
            return None
        return i0, i1, j0, j1

    def samples(self, i0, i1, j0, j1, z_mm: float) -> np.ndarray:
        """Sample points in S for the pixel box; shape (ni, nj, s*s, 3)."""
        rs, cs = self.spacing
        rc, cc = self.center
        s = self.sub.size
        ys = ((np.arange(i0, i1 + 1)[:, None] + self.sub[None, :]) - rc) * rs  # (ni, s)
        xs = ((np.arange(j0, j1 + 1)[:, None] + self.sub[None, :]) - cc) * cs  # (nj, s)
        ni, nj = ys.shape[0], xs.shape[0]
        pts = np.empty((ni, nj, s, s, 3))
        pts[..., 0] = xs[None, :, None, :]
        pts[..., 1] = ys[:, None, :, None]
        pts[..., 2] = z_mm
        return pts.reshape(ni, nj, s * s, 3)


def _unit_clip(x: np.ndarray) -> np.ndarray:
    """``np.clip(x, 0, 1)`` in place (the same values for any x but -0.0; without np.clip's call overhead)."""
    np.maximum(x, 0.0, out=x)
    return np.minimum(x, 1.0, out=x)


def _crossing_box(c: np.ndarray, t: np.ndarray, r: float, length: float, z_mm: float, pixel_mm: float):
    """``(x, y, hx, hy)`` (mm): the centre in the sub-plane ``z = z_mm`` of S of one crossing's section (a tube of
    radius ``r``, ``length``, its centreline point ``c`` and unit tangent ``t`` in S: three numbers each) and the
    half-extents of the box that holds it, two pixels (``pixel_mm``) wider."""
    # in-plane section: inside the ellipse (semi-axes a along the tangent's projection,
    # and r) about the tangent line's crossing; c itself is off the plane when a line
    # crossing was clipped to the tube's end
    shift = (c[2] - z_mm) / t[2] if abs(t[2]) > 1e-9 else math.inf
    if abs(shift) <= length:
        x, y = c[0] - shift * t[0], c[1] - shift * t[1]
        a = min(r / max(abs(t[2]), 1e-6), length + r)
    else:  # (nearly) parallel to the plane: a band along the segment
        x, y, a = c[0], c[1], length + r
    txy = math.hypot(t[0], t[1])
    ux, uy = (t[0] / txy, t[1] / txy) if txy > 1e-12 else (1.0, 0.0)
    margin = 2.0 * pixel_mm
    hx = math.sqrt((a * ux) ** 2 + (r * uy) ** 2) + margin
    hy = math.sqrt((a * uy) ** 2 + (r * ux) ** 2) + margin
    return x, y, hx, hy


def _coverage(perp_x, perp_y, dist, u, r, length, t_x, t_y, hs_x: float, hs_y: float) -> np.ndarray:
    """Fluid fraction of samples (arrays of one shape): ``perp_*`` the in-plane components of each sample's offset
    from the centreline (its length ``dist`` in 3-D), ``u`` its centreline parameter; ``r``, ``length`` the tube's
    radius and length and ``t_*`` its tangent's in-plane components in S (numbers, or arrays of the samples'
    shape); ``hs_*`` the half-footprint of a sample. A linear ramp across the sample's footprint at the wall and
    at the tube's ends."""
    if dist.all():  # (no sample on the centreline: nothing to silence)
        gx = np.abs(perp_x) / dist
        gy = np.abs(perp_y) / dist
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            gx = np.abs(perp_x) / dist
            gy = np.abs(perp_y) / dist
    w_r = hs_x * gx + hs_y * gy
    if not np.isfinite(w_r).all():  # a sample on the centreline (0 / 0)
        w_r = np.nan_to_num(w_r, nan=0.0)
    cov = _unit_clip(0.5 + (r - dist) / np.maximum(w_r, 1e-12))
    inside_mm = np.minimum(u, 1.0 - u) * length
    w_e = hs_x * np.abs(t_x) + hs_y * np.abs(t_y)
    cov *= _unit_clip(0.5 + inside_mm / np.maximum(w_e, 1e-12))
    return cov


def _render_crossing(tube, u_c: float, T_F_from_S: np.ndarray, z_mm: float, grid: _Grid, layer: np.ndarray):
    """Fluid fraction of one tube crossing in the sub-plane ``z = z_mm`` of S, max-composited into ``layer``."""
    R = T_F_from_S[:3, :3]
    tF = T_F_from_S[:3, 3]
    c = (tube.points(u_c)[0] - tF) @ R
    t = tube.tangents(u_c)[0] @ R
    r = 0.5 * tube.diameter
    length = tube.length_mm
    box = grid.box(*_crossing_box(c, t, r, length, z_mm, max(grid.spacing)))
    if box is None:
        return
    i0, i1, j0, j1 = box
    p = grid.samples(i0, i1, j0, j1, z_mm)
    pc = p - c
    s0 = pc @ t  # arc length along the tangent line
    u = u_c + s0 / length
    if tube.curved:
        # re-project on the exact centreline: the nearest point to second order
        q = (tube.points(u.ravel()) - tF) @ R
        tq = tube.tangents(u.ravel()) @ R
        d = p.reshape(-1, 3) - q
        along = np.einsum("ij,ij->i", d, tq)
        perp = (d - along[:, None] * tq).reshape(p.shape)
        u = u + along.reshape(u.shape) / length
    else:
        perp = pc - s0[..., None] * t
    dist = np.sqrt(np.einsum("...i,...i->...", perp, perp))
    rs, cs = grid.spacing
    cov = _coverage(perp[..., 0], perp[..., 1], dist, u, r, length, t[0], t[1], cs / grid.sub.size, rs / grid.sub.size)
    frac = cov[..., 0] if cov.shape[-1] == 1 else cov.mean(axis=-1)  # (one sample a pixel: its own value)
    region = layer[i0 : i1 + 1, j0 : j1 + 1]
    np.maximum(region, frac, out=region)


def check_grid(shape, pixel_spacing_mm, center_px, supersample, thickness_samples, slice_thickness_mm):
    """The checked grid: ``(rows, cols), (row_mm, col_mm), (rc, cc)`` (default centre: the image centre)."""
    rows, cols = (int(v) for v in shape)
    if rows < 1 or cols < 1:
        raise ValueError(f"shape must be positive, got {tuple(shape)}")
    rs, cs = (float(v) for v in pixel_spacing_mm)
    if not (rs > 0 and cs > 0 and math.isfinite(rs) and math.isfinite(cs)):
        raise ValueError(f"pixel_spacing_mm must be two positive numbers, got {tuple(pixel_spacing_mm)}")
    if int(supersample) < 1 or int(thickness_samples) < 1:
        raise ValueError("supersample and thickness_samples must be >= 1")
    if not (slice_thickness_mm >= 0 and math.isfinite(slice_thickness_mm)):
        raise ValueError(f"slice_thickness_mm must be >= 0, got {slice_thickness_mm}")
    if center_px is None:
        center_px = ((rows - 1) / 2.0, (cols - 1) / 2.0)
    return (rows, cols), (rs, cs), (float(center_px[0]), float(center_px[1]))


def render_tubes(
    tubes,
    T_F_from_S: np.ndarray,
    shape=(256, 256),
    pixel_spacing_mm=(0.5, 0.5),
    slice_thickness_mm: float = 0.0,
    center_px=None,
    supersample: int = 4,
    thickness_samples: int = 5,
) -> np.ndarray:
    """Fluid fraction image of any :class:`~chic_register.model.tubes.Tube` objects (in F); shape (rows, cols), in [0, 1]."""
    shape, spacing, center = check_grid(
        shape, pixel_spacing_mm, center_px, supersample, thickness_samples, slice_thickness_mm
    )
    T = np.asarray(T_F_from_S, dtype=float)
    grid = _Grid(shape, spacing, center, sample_offsets(int(supersample)))
    offsets = _plane_offsets_mm(float(slice_thickness_mm), int(thickness_samples))
    normal = T[:3, 2]
    image = np.zeros(shape)
    layer = np.empty(shape)
    for dz in offsets:
        layer.fill(0.0)
        origin = T[:3, 3] + dz * normal
        for tube in tubes:
            margin = 4.0 * tube.diameter + 0.5 * float(slice_thickness_mm)
            for u_c in tube.section_params(origin, normal, margin):
                _render_crossing(tube, float(u_c), T, float(dz), grid, layer)
        image += layer
    image /= offsets.size
    return np.clip(image, 0.0, 1.0)


def render_slice(
    geom: FiducialGeometry,
    T_F_from_S: np.ndarray,
    shape=(256, 256),
    pixel_spacing_mm=(0.5, 0.5),
    slice_thickness_mm: float = 0.0,
    center_px=None,
    supersample: int = 4,
    thickness_samples: int = 5,
) -> np.ndarray:
    """Fluid fraction of each voxel of a slice through ``geom``; shape (rows, cols), float64 in [0, 1].

    ``T_F_from_S`` (4x4) places the slice frame S in F; the pixel (i, j)
    centre is at S coordinates ``((j - cc) * col_spacing, (i - rc) * row_spacing, 0)``
    with ``(rc, cc) = center_px`` (default: the image centre). Partial volume
    covers the pixel area (``supersample``² samples) and the slice thickness
    (``thickness_samples`` sub-planes over ``slice_thickness_mm``; one plane if 0).
    """
    return render_tubes(
        geom.tubes, T_F_from_S, shape, pixel_spacing_mm, slice_thickness_mm,
        center_px, supersample, thickness_samples,
    )


def render_windows(windows, T_F_from_S: np.ndarray, pixel_spacing_mm, slice_thickness_mm: float,
                   thickness_samples: int) -> list[np.ndarray]:
    """Each tube drawn alone in its own window, all at once: ``windows`` ``[(tube, r0, c0, h, w)]``, one image
    (h, w) each, as ``render_tubes([tube], T_F_from_S, (h, w), pixel_spacing_mm, slice_thickness_mm,
    center_px=(-r0, -c0), supersample=1, thickness_samples=thickness_samples)`` draws it (to rounding).

    The verification (:mod:`chic_register.verify.windows`) draws a dozen small windows per pose: one pass of array
    arithmetic over every section's pixels replaces one per section and sub-plane, whose cost was numpy's per-call
    overhead. The same crossings, boxes and coverage (:func:`_crossing_box`, :func:`_coverage`).
    """
    rs, cs = (float(v) for v in pixel_spacing_mm)
    T = np.asarray(T_F_from_S, dtype=float)
    tF, normal = T[:3, 3], T[:3, 2]
    offsets = _plane_offsets_mm(float(slice_thickness_mm), int(thickness_samples))
    L = offsets.size
    sizes = [h * w for _, _, _, h, w in windows]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    total = int(starts[-1])
    # the crossings, window by window (a window's samples are then contiguous), each sub-plane's in turn
    cross = []  # (window, sub-plane, u_c)
    origins = [tF + dz * normal for dz in offsets]
    for n, (tube, *_) in enumerate(windows):
        margin = 4.0 * tube.diameter + 0.5 * float(slice_thickness_mm)
        for l, o in enumerate(origins):
            cross.extend((n, l, float(u)) for u in tube.section_params(o, normal, margin))
    buf = np.zeros((L, total))
    if cross and total:
        _draw_crossings(windows, cross, T, offsets, (rs, cs), starts, buf)
    image = buf[0].copy()
    for layer in buf[1:]:
        image += layer
    image /= L
    np.clip(image, 0.0, 1.0, out=image)
    return [image[starts[n]:starts[n + 1]].reshape(h, w) for n, (_, _, _, h, w) in enumerate(windows)]


def _draw_crossings(windows, cross, T, offsets, spacing, starts, buf) -> None:
    """:func:`render_windows`' crossings ``[(window, sub-plane, u_c)]`` (window by window) max-composited into
    ``buf`` (sub-planes, all windows' pixels)."""
    rs, cs = spacing
    R, tF = T[:3, :3], T[:3, 3]
    px = max(rs, cs)
    uc = np.array([c[2] for c in cross])
    C = np.empty((len(cross), 3))
    Tg = np.empty((len(cross), 3))
    a = 0
    while a < len(cross):  # a tube's points and tangents in one call each (its crossings are contiguous)
        n = cross[a][0]
        b = a + 1
        while b < len(cross) and cross[b][0] == n:
            b += 1
        C[a:b] = windows[n][0].points(uc[a:b])
        Tg[a:b] = windows[n][0].tangents(uc[a:b])
        a = b
    C = (C - tF) @ R
    Tg = Tg @ R
    rows = []  # per crossing drawn: its box and what its samples need
    total = buf.shape[1]
    grids = {}
    for m, ((n, l, u), c, t) in enumerate(zip(cross, C.tolist(), Tg.tolist())):
        tube, r0, c0, h, w = windows[n]
        if n not in grids:
            grids[n] = _Grid((h, w), (rs, cs), (-float(r0), -float(c0)), None)
        r, length, z = 0.5 * tube.diameter, tube.length_mm, float(offsets[l])
        box = grids[n].box(*_crossing_box(c, t, r, length, z, px))
        if box is not None:
            i0, i1, j0, j1 = box  # (a curved tube is a helix: the Tube protocol's only curved kind)
            helix = (tube.radius, tube.theta0_deg, tube.pitch_deg_per_mm, tube.z0, tube.z1) if tube.curved else ()
            rows.append((n, l, i1 - i0 + 1, j1 - j0 + 1, *c, *t, u, length, r, z, i0 + r0, j0 + c0,
                         l * total + int(starts[n]) + i0 * w + j0, w, *(helix or (0.0,) * 5), bool(helix)))
    if not rows:
        return
    rows.sort(key=lambda row: row[-1])  # the helices' crossings last: their samples are the arrays' tail
    P = np.array(rows, dtype=float).T  # (fields, crossings drawn)
    win, lay = P[0].astype(int), P[1].astype(int)
    ni, nj = P[2].astype(int), P[3].astype(int)
    count = ni * nj
    Q = np.repeat(P[4:], count, axis=1)  # each sample's crossing's fields
    cvec, tvec, u_c, length, radius, z_mm, row0, col0, base, width = (
        Q[0:3], Q[3:6], Q[6], Q[7], Q[8], Q[9], Q[10], Q[11], Q[12], Q[13])
    local = np.arange(Q.shape[1]) - np.repeat(np.cumsum(count) - count, count)
    nj_s = np.repeat(nj, count)
    row = local // nj_s
    col = local - row * nj_s
    # sample points in S (one sample a pixel, at its centre), as _Grid.samples
    p = np.stack([(col + col0) * cs, (row + row0) * rs, z_mm])
    pc = p - cvec
    s0 = (pc * tvec).sum(axis=0)  # arc length along the tangent line
    u = u_c + s0 / length
    perp = pc - s0 * tvec
    n_lines = int(count[P[-1] == 0].sum())
    if n_lines < Q.shape[1]:  # helices: re-project on the exact centreline (the nearest point to second order)
        k = slice(n_lines, None)
        rad, th0, pitch, z0, z1 = Q[14:19, k]
        uk = u[k]
        q = (helix_points(rad, th0, pitch, z0, z0 + uk * (z1 - z0)) - tF) @ R
        tq = (helix_tangents(rad, th0, pitch, z0, z1, uk) @ R).T
        d = p[:, k] - q.T
        along = (d * tq).sum(axis=0)
        perp[:, k] = d - along * tq
        u[k] = uk + along / length[k]
    dist = np.sqrt((perp * perp).sum(axis=0))
    frac = _coverage(perp[0], perp[1], dist, u, radius, length, tvec[0], tvec[1], cs, rs)
    dest = (base + row * width + col).astype(np.intp)
    flat = buf.reshape(-1)
    key = (win * len(offsets) + lay).tolist()
    if len(set(key)) == len(key):
        flat[dest] = frac  # (the buffer is zero there: one section per window and sub-plane)
        return
    # sections of one window and sub-plane may overlap (a helix crossing a plane twice): composited in turns
    turn, seen = [], {}
    for v in key:
        turn.append(seen.get(v, 0))
        seen[v] = turn[-1] + 1
    turn = np.repeat(turn, count)
    for t in range(max(seen.values())):
        sel = turn == t
        flat[dest[sel]] = np.maximum(flat[dest[sel]], frac[sel])
