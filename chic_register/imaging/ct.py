"""Synthetic CT slices: a slice's rod fractions turned into Hounsfield units, with plates, a skull, metal and noise.

A CT slice of a fiducial is air (-1000 HU) outside everything, the plastic
plates the rods sit in (a slab ``plate_mm`` thick around each plane that holds
three or more coplanar line tubes, over the tubes' extent), the rods' fill at
``rod_hu`` with the renderer's partial volume, and Gaussian noise of
``noise_hu``; outside the reconstruction circle (the image's inscribed circle)
the scanner's padding value. Distractors that are bright but no rods: a skull
(an elliptic ring of bone around brain, centred in the image) and metal (a
small dense blob with straight bright and dark streaks radiating from it
through the image, fading with distance).

Pixel (row i, col j) has its centre at slice-frame coordinates
``x = (j - cc) * col_spacing``, ``y = (i - rc) * row_spacing`` with
``(rc, cc) = center_px``, as in :mod:`chic_register.imaging.render`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from chic_register.imaging.render import sample_offsets
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import LineTube

#: Air and water in Hounsfield units.
AIR_HU = -1000.0
WATER_HU = 0.0
#: A CT's default grid: 512 x 512 pixels of 0.6 mm (a 307 mm field of view) and 1 mm slices.
CT_SHAPE = (512, 512)
CT_PIXEL_MM = 0.6
CT_THICKNESS_MM = 1.0
#: Coplanar tubes: every endpoint within this distance (mm) of the plane.
COPLANAR_MM = 0.05


@dataclass(frozen=True)
class CTScene:
    """What a simulated CT slice holds besides the rods, in Hounsfield units and mm.

    ``rod_hu``: the rods' contrast fill; ``plate_hu``/``plate_mm``: the plastic
    plates (0 mm: none); ``plate_margin_mm``: how far a plate reaches beyond its
    outermost tubes; ``noise_hu``: the Gaussian noise's sigma; ``padding_hu``:
    the value outside the reconstruction circle (None: no circle);
    ``skull``: an elliptic bone ring of semi-axes ``skull_mm`` (x, y in the
    slice), ``skull_thickness_mm`` thick at ``skull_hu``, brain at
    ``brain_hu`` inside; ``metal``: a dense blob of ``metal_mm`` diameter at
    ``metal_hu`` at ``metal_at_mm`` (slice x, y) with ``streaks`` straight
    streaks of +-``streak_hu`` radiating from it, fading over
    ``streak_fade_mm``.
    """

    rod_hu: float = 1500.0
    plate_hu: float = 150.0
    plate_mm: float = 4.0
    plate_margin_mm: float = 8.0
    noise_hu: float = 18.0
    padding_hu: float | None = -2048.0
    skull: bool = False
    skull_mm: tuple[float, float] = (70.0, 88.0)
    skull_thickness_mm: float = 6.0
    skull_hu: float = 1000.0
    brain_hu: float = 40.0
    metal: bool = False
    metal_at_mm: tuple[float, float] = (25.0, -40.0)
    metal_mm: float = 3.0
    metal_hu: float = 3000.0
    streaks: int = 8
    streak_hu: float = 500.0
    streak_fade_mm: float = 40.0

    def __post_init__(self):
        finite = [v for v in asdict(self).values() if isinstance(v, float)] + [*self.skull_mm, *self.metal_at_mm]
        if not all(math.isfinite(v) for v in finite):
            raise ValueError("CT scene values must be finite numbers")
        if self.plate_mm < 0 or self.noise_hu < 0 or self.streaks < 0 or self.streak_fade_mm <= 0:
            raise ValueError("plate_mm, noise_hu and streaks must be >= 0, streak_fade_mm > 0")

    def to_dict(self) -> dict:
        """JSON-ready settings."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass(frozen=True)
class Plate:
    """A plastic plate: the plane through ``origin`` spanned by unit vectors ``u``, ``v`` (normal ``n``), over
    ``u_range``/``v_range`` (mm) of it; all in F."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    n: np.ndarray
    u_range: tuple[float, float]
    v_range: tuple[float, float]


def coplanar_plates(geom: FiducialGeometry, margin_mm: float) -> list[Plate]:
    """The plates of a geometry: each plane that holds three or more of its line tubes (two parallel rods alone
    span a plane that need not be a plate), over the tubes' extent plus ``margin_mm``."""
    lines = [t for t in geom.tubes if isinstance(t, LineTube)]
    ends = {t.id: np.array([t.p0, t.p1], float) for t in lines}
    plates, seen = [], set()
    for i, a in enumerate(lines):
        for b in lines[i + 1:]:
            pa, pb = ends[a.id], ends[b.id]
            d = pa[1] - pa[0]
            n = np.cross(d, pb[0] - pa[0])
            if np.linalg.norm(n) < 1e-6:
                n = np.cross(d, pb[1] - pa[0])
            if np.linalg.norm(n) < 1e-6:
                continue  # the same line
            n = n / np.linalg.norm(n)
            members = frozenset(t.id for t in lines if np.all(np.abs((ends[t.id] - pa[0]) @ n) < COPLANAR_MM))
            if len(members) < 3 or members in seen:
                continue
            seen.add(members)
            u = d / np.linalg.norm(d)
            v = np.cross(n, u)
            pts = np.concatenate([ends[m] for m in members]) - pa[0]
            pu, pv = pts @ u, pts @ v
            plates.append(Plate(pa[0], u, v, n, (pu.min() - margin_mm, pu.max() + margin_mm),
                                (pv.min() - margin_mm, pv.max() + margin_mm)))
    return plates


def _slice_points(shape, spacing, center, T_F_from_S, offsets_px, z_mm):
    """F coordinates of sample points of every pixel in the sub-plane ``z = z_mm`` of S; shape (rows, cols, s*s, 3)."""
    rows, cols = shape
    rs, cs = spacing
    ys = ((np.arange(rows)[:, None] + offsets_px) - center[0]) * rs  # (rows, s)
    xs = ((np.arange(cols)[:, None] + offsets_px) - center[1]) * cs  # (cols, s)
    s = offsets_px.size
    R, t = T_F_from_S[:3, :3], T_F_from_S[:3, 3]
    X = xs[None, :, None, :]
    Y = ys[:, None, :, None]
    out = np.empty((rows, cols, s, s, 3))
    for k in range(3):
        out[..., k] = R[k, 0] * X + R[k, 1] * Y + R[k, 2] * z_mm + t[k]
    return out.reshape(rows, cols, s * s, 3)


def plate_fraction(plates: list[Plate], thickness_mm: float, T_F_from_S, shape, spacing, center,
                   supersample: int = 2, thickness_samples: int = 3) -> np.ndarray:
    """The share of each pixel's volume inside a plate of ``thickness_mm``; shape (rows, cols)."""
    out = np.zeros(shape)
    if not plates or thickness_mm <= 0:
        return out
    sub = sample_offsets(supersample)
    zs = sample_offsets(thickness_samples) * thickness_mm if thickness_mm > 0 else np.zeros(1)
    for z in zs:
        q = _slice_points(shape, spacing, center, T_F_from_S, sub, z)
        inside = np.zeros(q.shape[:3], bool)
        for p in plates:
            d = q - p.origin
            w = np.abs(d @ p.n) <= 0.5 * thickness_mm
            du, dv = d @ p.u, d @ p.v
            w &= (du >= p.u_range[0]) & (du <= p.u_range[1]) & (dv >= p.v_range[0]) & (dv <= p.v_range[1])
            inside |= w
        out += inside.mean(axis=2)
    return out / len(zs)


def _pixel_xy(shape, spacing, center, sub):
    """Slice-frame sample coordinates (mm): X (1, cols, 1, s) and Y (rows, 1, s, 1)."""
    rows, cols = shape
    rs, cs = spacing
    ys = ((np.arange(rows)[:, None] + sub) - center[0]) * rs
    xs = ((np.arange(cols)[:, None] + sub) - center[1]) * cs
    return xs[None, :, None, :], ys[:, None, :, None]


def _ellipse_inside(X, Y, a, b):
    return (X / a) ** 2 + (Y / b) ** 2 <= 1.0


def skull_image(scene: CTScene, shape, spacing, center, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(head, bone)`` shares of each pixel (rows, cols): inside the skull's outer ellipse, and in its ring."""
    X, Y = _pixel_xy(shape, spacing, center, sample_offsets(supersample))
    a, b = scene.skull_mm
    t = scene.skull_thickness_mm
    outer = _ellipse_inside(X, Y, a, b)
    inner = _ellipse_inside(X, Y, max(a - t, 1e-3), max(b - t, 1e-3))
    return outer.mean(axis=(2, 3)), (outer & ~inner).mean(axis=(2, 3))


def metal_image(scene: CTScene, shape, spacing, center, rng: np.random.Generator,
                supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(share, streaks_hu)`` (rows, cols): each pixel's share of the metal blob, and the streaks' HU: straight
    lines through the metal at random angles, each bright or dark, about a pixel wide, fading with distance."""
    X, Y = _pixel_xy(shape, spacing, center, sample_offsets(supersample))
    x0, y0 = scene.metal_at_mm
    dx, dy = X - x0, Y - y0
    share = (np.hypot(dx, dy) <= 0.5 * scene.metal_mm).mean(axis=(2, 3))
    px = min(spacing)
    x, y = dx.mean(axis=3)[..., 0], dy.mean(axis=2)[..., 0]  # pixel centres: (1, cols), (rows, 1)
    r = np.hypot(x, y)
    fade = 1.0 / (1.0 + r / scene.streak_fade_mm)
    streaks = np.zeros(shape)
    for k in range(scene.streaks):
        phi = math.pi * (k + rng.uniform(0.2, 0.8)) / scene.streaks
        across = -x * math.sin(phi) + y * math.cos(phi)
        sign = 1.0 if k % 2 == 0 else -1.0
        streaks += sign * scene.streak_hu * rng.uniform(0.6, 1.0) * np.exp(-0.5 * (across / px) ** 2)
    return share, streaks * fade


def hounsfield_slice(geom: FiducialGeometry, rods: np.ndarray, T_F_from_S, spacing, center, thickness_mm: float,
                     scene: CTScene, rng: np.random.Generator) -> np.ndarray:
    """A CT slice in HU (rows, cols) from ``rods``, the rods' fluid share of each pixel (the renderer's partial
    volume): air, plates, skull and metal as ``scene`` says, the rods' fill over them, then noise and padding."""
    shape = rods.shape
    hu = np.full(shape, AIR_HU)
    if scene.plate_mm > 0:
        plates = coplanar_plates(geom, scene.plate_margin_mm)
        share = plate_fraction(plates, scene.plate_mm, np.asarray(T_F_from_S, float), shape, spacing, center)
        hu += share * (scene.plate_hu - AIR_HU)
    if scene.skull:
        head, bone = skull_image(scene, shape, spacing, center)
        hu += (head - bone) * (scene.brain_hu - hu) + bone * (scene.skull_hu - hu)
    hu = hu * (1.0 - rods) + rods * scene.rod_hu
    if scene.metal:
        share, streaks = metal_image(scene, shape, spacing, center, rng)
        hu = hu * (1.0 - share) + share * scene.metal_hu + streaks
    if scene.noise_hu > 0:
        hu = hu + rng.normal(0.0, scene.noise_hu, shape)
    if scene.padding_hu is not None:
        rows, cols = shape
        i, j = np.ogrid[:rows, :cols]
        radius = 0.5 * min(rows * spacing[0], cols * spacing[1])
        outside = np.hypot((i - (rows - 1) / 2) * spacing[0], (j - (cols - 1) / 2) * spacing[1]) > radius
        hu[np.broadcast_to(outside, shape)] = scene.padding_hu
    return hu
