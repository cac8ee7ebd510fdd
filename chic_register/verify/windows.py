"""The verification's tube windows (:mod:`chic_register.verify.pixels`): the model rendered around each tube's section
with its neighbours (:func:`tube_windows`), fitted to the pixels (:func:`fit_window`), and what the fit says: the
residual energy beyond the noise (:func:`shape_excess`), where the section lies against where the pose puts it
(:func:`section_shift`), and its spread along rows and columns (:func:`window_spread`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.filters import dilate
from chic_register.imaging.render import render_windows
from chic_register.model.tube_model import plane_crossings, section_box, section_extent
from chic_register.util.lapack import lstsq

#: Render settings: one sample a pixel (:func:`chic_register.imaging.render.render_windows`; the renderer's coverage ramp
#: anti-aliases edges already) and at most this many sub-planes over the slab.
MAX_THICKNESS_SAMPLES = 3
#: One more sub-plane for every this many pixels of slab smear along a section (the renderer averages the
#: sub-planes; between them the section's end is a ramp, within the shape tolerance at 4 px).
SMEAR_PX_PER_SAMPLE = 4.0


@dataclass
class TubeWindow:
    k: int
    r0: int
    c0: int
    own: np.ndarray  # rendered section of this tube in the window
    others: np.ndarray  # other tubes' sections in the window


def tube_windows(geom, model, T_F_from_I, shape, spacing, thickness_mm, margin_px: float = 2.0,
             canvas_only: bool = False):
    """``(windows, canvas)``: per tube whose section lies wholly inside the image its window with its own and
    its neighbours' renders, and the whole model image (shape of the image, every section pasted in);
    ``canvas_only``: no windows (``[]``), the canvas alone (a rival pose's model image).

    Each tube is rendered once, in its own window (its section's extent,
    :func:`chic_register.model.tube_model.section_extent`, plus ``margin_px``); a window's
    neighbours are the other tubes' renders pasted where they overlap it.
    """
    rs, cs = spacing
    px = max(rs, cs)
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=0.5 * float(model.diameter_mm.max()) + thickness_mm)
    half_len, half_wid, u = section_extent(model, tan, thickness_mm)
    ex, ey = (e + margin_px * px for e in section_box(half_len, half_wid, u))
    txy = np.hypot(tan[:, 0], tan[:, 1])
    smear_px = float(np.max(thickness_mm * txy / np.maximum(np.abs(tan[:, 2]), 1e-3))) / px if txy.size else 0.0
    ts = int(min(MAX_THICKNESS_SAMPLES, max(1, math.ceil(smear_px / SMEAR_PX_PER_SAMPLE) + 1)))
    H, W = shape
    todo = []
    for k in np.flatnonzero(found):
        r0, r1 = int(math.floor((q[k, 1] - ey[k]) / rs)), int(math.ceil((q[k, 1] + ey[k]) / rs)) + 1
        c0, c1 = int(math.floor((q[k, 0] - ex[k]) / cs)), int(math.ceil((q[k, 0] + ex[k]) / cs)) + 1
        inside = r0 >= 0 and c0 >= 0 and r1 <= H and c1 <= W and r1 - r0 <= H // 2 and c1 - c0 <= W // 2
        r0, r1, c0, c1 = max(r0, 0), min(r1, H), max(c0, 0), min(c1, W)
        if r1 - r0 < 2 or c1 - c0 < 2 or (r1 - r0) * (c1 - c0) > H * W // 4:
            continue
        todo.append((int(k), r0, c0, r1 - r0, c1 - c0, inside))
    imgs = render_windows([(geom.tubes[k], r0, c0, h, w) for k, r0, c0, h, w, _ in todo], T_F_from_I, (rs, cs),
                          thickness_mm, ts) if todo else []
    boxes = {k: (r0, c0, img, inside) for (k, r0, c0, _, _, inside), img in zip(todo, imgs) if img.max() > 0}
    out = []
    canvas = np.zeros(shape)
    for k, (r0, c0, img, inside) in boxes.items():
        sub = canvas[r0:r0 + img.shape[0], c0:c0 + img.shape[1]]
        np.maximum(sub, img, out=sub)
        if not inside or canvas_only:
            continue  # (partly) outside the image: nothing to check, but it is a neighbour of the others
        h, w = img.shape
        others = np.zeros_like(img)
        for i, (R0, C0, oimg, _) in boxes.items():
            if i == k:
                continue
            a0, b0 = max(r0, R0), max(c0, C0)
            a1, b1 = min(r0 + h, R0 + oimg.shape[0]), min(c0 + w, C0 + oimg.shape[1])
            if a0 < a1 and b0 < b1:
                sub = others[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
                np.maximum(sub, oimg[a0 - R0:a1 - R0, b0 - C0:b1 - C0], out=sub)
        out.append(TubeWindow(k, r0, c0, img, others))
    return out, canvas


def fit_window(pixels, w: TubeWindow):
    """Least squares over the window: ``(coef, y, fit)`` of ``pixels = b + a section + a' neighbours``
    (the gains apart: presence) and ``fit1`` of ``pixels = b + a max(section, neighbours)`` (one fluid level,
    composited as the image is: the shape test). None when degenerate."""
    h, wd = w.own.shape
    y = np.asarray(pixels[w.r0:w.r0 + h, w.c0:w.c0 + wd], float).ravel()
    m = w.own.ravel()
    o = w.others.ravel()
    cols = [np.ones_like(m), m] + ([o] if o.max() > 0.05 else [])
    A = np.stack(cols, axis=1)
    coef, rank = lstsq(A, y)
    if rank < A.shape[1]:
        return None
    A1 = np.stack([np.ones_like(m), np.maximum(m, o)], axis=1)
    coef1 = lstsq(A1, y)[0]
    fit1 = A1 @ coef1
    if len(cols) == 3:  # a neighbour in the window: real rods differ in fluid level (fill, bubbles, coil)
        fit2 = _composite_two_levels(y, m, o, coef)
        if fit2 is not None and float((y - fit2) @ (y - fit2)) < float((y - fit1) @ (y - fit1)):
            fit1 = fit2
    return coef, y, fit1


def _composite_two_levels(y, m, o, coef, rounds: int = 3):
    """``b + max(a m, a' o)`` fitted to ``y``: the section and its neighbours each at their own fluid level,
    composited as the image is (each pixel belongs to the brighter term; a few alternating least squares)."""
    b, a, a2 = (float(v) for v in coef)
    fit = prev = None
    for _ in range(rounds):
        mine = a * m >= a2 * o
        if prev is not None and np.array_equal(mine, prev):
            return fit  # the same split of the pixels: the same least squares, the same fit, every round from here on
        prev = mine
        A = np.stack([np.ones_like(m), np.where(mine, m, 0.0), np.where(mine, 0.0, o)], axis=1)
        c, rank = lstsq(A, y)
        if rank < 3 or not (c[1] > 0 and c[2] > 0):
            return fit
        b, a, a2 = (float(v) for v in c)
        fit = A @ c
    return fit


def shape_excess(w: TubeWindow, y: np.ndarray, fit: np.ndarray, sigma: float, level: float):
    """``(excess, allowed_noise, support)`` of a fitted window (:func:`fit_window`): the residual energy over
    the section (its support grown by a pixel) beyond the noise, as a share of the section's energy, and four
    noise sigmas of that term."""
    own = w.own.ravel()
    energy = max(float(own @ own), 1e-12)
    sup = dilate(w.own > 0.02, 1).ravel()
    res = (y - fit)[sup]
    excess = max(float(res @ res) - sup.sum() * sigma * sigma, 0.0) / (level * level * energy)
    chi_tol = 4.0 * math.sqrt(2.0 * sup.sum()) * sigma * sigma / (level * level * energy)
    return excess, chi_tol, sup


def section_shift(w, y: np.ndarray, coef: np.ndarray, sigma: float) -> tuple[float, float]:
    """``(shift, standard error)`` in pixels: the in-plane shift of a tube's rendered section that best explains the
    residual of its window's fit (:func:`fit_window`'s ``coef``), to first order (the section's gradient times its
    gain, with an offset), and the standard error of its length under pixel noise ``sigma``. ``(0, inf)`` when
    degenerate."""
    own = w.own
    res = y - coef[0] - coef[1] * own.ravel()
    if coef.size > 2:
        res -= coef[2] * w.others.ravel()
    g = np.empty((2,) + own.shape)  # central differences, one-sided at the window's edges (np.gradient's, cheaper)
    g[0, 1:-1] = 0.5 * (own[2:] - own[:-2])
    g[0, 0], g[0, -1] = own[1] - own[0], own[-1] - own[-2]
    g[1, :, 1:-1] = 0.5 * (own[:, 2:] - own[:, :-2])
    g[1, :, 0], g[1, :, -1] = own[:, 1] - own[:, 0], own[:, -1] - own[:, -2]
    g = g.reshape(2, -1)
    g -= g.mean(axis=1, keepdims=True)  # the offset's column projected out
    a = float(coef[1])
    (grr, grc), (_, gcc) = (g @ g.T).tolist()
    det = grr * gcc - grc * grc
    if not a * a * det > 0:
        return 0.0, math.inf
    br, bc = (g @ res).tolist()
    dr, dc = -(gcc * br - grc * bc) / (a * det), -(grr * bc - grc * br) / (a * det)  # y ~ a own(x - d): -a grad . d
    n = math.hypot(dr, dc)
    ur, uc = (dr / n, dc / n) if n > 0 else (1.0, 0.0)
    var = (gcc * ur * ur - 2 * grc * ur * uc + grr * uc * uc) / (a * a * det)  # u^T (a^2 G)^-1 u
    return n, sigma * math.sqrt(max(var, 0.0))


def window_spread(w: np.ndarray):
    """Weighted variance along rows and columns (pixels^2) of weights ``w`` (h, w); None if empty."""
    total = float(w.sum())
    if not total > 0:
        return None
    r = np.arange(w.shape[0], dtype=float)
    c = np.arange(w.shape[1], dtype=float)
    wr, wc = w.sum(axis=1), w.sum(axis=0)
    mr, mc = wr @ r / total, wc @ c / total
    vr, vc = wr @ (r - mr) ** 2 / total, wc @ (c - mc) ** 2 / total
    if not (vr > 0 and vc > 0):
        return None
    return np.array([vr, vc])


def aspect_error(w: np.ndarray, noisy: np.ndarray, spread: np.ndarray, sigma: float) -> float:
    """Standard error of ``sqrt(vc / vr)`` (the aspect of :func:`window_spread`'s variances ``spread``) of weights
    ``w`` (h, w) when each pixel of ``noisy`` (h, w, bool) carries noise ``sigma``, to first order (relative):
    ``d vr / d w_i = ((r_i - m_r)^2 - vr) / sum w``, and likewise along the columns."""
    total = float(w.sum())
    r = np.arange(w.shape[0], dtype=float)[:, None]
    c = np.arange(w.shape[1], dtype=float)[None, :]
    mr, mc = float(w.sum(axis=1) @ r[:, 0]) / total, float(w.sum(axis=0) @ c[0]) / total
    g = 0.5 * (((c - mc) ** 2 - spread[1]) / spread[1] - ((r - mr) ** 2 - spread[0]) / spread[0]) / total
    return sigma * float(np.sqrt(np.sum(g[noisy] ** 2)))


#: Relative error of the rendered model itself (supersampling 2 x 2, a few sub-planes): a residual energy this
#: share of the section's energy is model error, not misfit.
MODEL_FLOOR = 0.03
