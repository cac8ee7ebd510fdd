"""MRI slices rendered from the printed body's mesh through k-space, independently of the solver's renderer.

The solver's own simulator (:mod:`chic_register.imaging.render`) draws each
tube from the same section model the solver fits, so a study on its images
cannot see an error shared by both. This model shares nothing with it but the
pose convention:

- fluid: the tube wall (between the body's inner and outer radii, over its
  length) minus the printed body, decided on the body's triangle mesh (the
  ``body.stl`` a design build writes): a point is body when a ray in the
  plane crosses the mesh's section an odd number of times;
- through-plane: the small-tip excitation profile of a Hann-windowed sinc
  pulse (its full width at half maximum is the slice thickness), sampled on
  sub-planes across twice the thickness, weights summing to 1;
- in-plane: fluid occupancy point-sampled on a grid ``oversample`` times finer
  than the pixels, its exact 2-D DFT cropped to the central matrix (what the
  scanner acquires: a band-limited image, with its Gibbs ringing and point
  spread), an optional k-space filter, the inverse DFT;
- noise: complex Gaussian in image space, then the magnitude (Rician), with
  sigma = 1 / ``snr`` (fluid has signal 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.body import Body
from chic_register.model.pose import apply, invert, rigid, slice_frame
from chic_register.model.slices import Slice

KSPACE_FILTERS = ("none", "hamming", "tukey")

#: Time-bandwidth product of the sinc excitation pulse (a common clinical 2-D pulse).
PULSE_TBW = 4.0

#: The fluid region stays this far inside the body's analytic wall radii: the tessellated cylinders lie up to the
#: mesh's chord tolerance inside them, and no channel comes this close to either surface.
WALL_MARGIN_MM = 0.05


@dataclass(frozen=True)
class KSpaceSlice:
    """A rendered slice: ``slice.pixels`` (rows, cols) magnitude, and the fiducial's true pose in its scanner."""

    slice: Slice
    T_scanner_from_fiducial: np.ndarray


def read_body_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """A body mesh file (``body.stl`` of a design build, in F): vertices (V, 3) mm and faces (F, 3)."""
    import trimesh  # deferred: only a study reading a mesh file needs it

    mesh = trimesh.load_mesh(str(path), process=True)
    if not mesh.is_watertight:
        raise ValueError(f"{path}: the body mesh is not closed; fluid cannot be told from body")
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)


def slice_profile(thickness_mm: float, n_planes: int = 24, tbw: float = PULSE_TBW):
    """Sub-plane offsets (n_planes,) in mm across 2 x ``thickness_mm`` and their profile weights (sum 1).

    The profile is the Fourier transform of a Hann-windowed sinc pulse of
    time-bandwidth ``tbw`` (small-tip approximation), scaled so that its pass
    band is ``thickness_mm`` wide.
    """
    z_mm = (np.arange(n_planes) + 0.5) / n_planes * 2.0 * thickness_mm - thickness_mm
    tau = np.linspace(-0.5, 0.5, 1025)  # pulse time over its duration
    pulse = np.sinc(tbw * tau) * (0.5 + 0.5 * np.cos(2.0 * np.pi * tau))
    freq = tbw * z_mm / thickness_mm  # offset in units of the pulse's bandwidth: |freq| < tbw / 2 is the pass band
    profile = np.abs(np.exp(-2j * np.pi * freq[:, None] * tau[None, :]) @ pulse)
    return z_mm, profile / profile.sum()


def kspace_window(n: int, kind: str) -> np.ndarray:
    """1-D k-space filter (n,) over centred frequency indices -n/2 .. n/2-1, 1 at k = 0."""
    if kind not in KSPACE_FILTERS:
        raise ValueError(f"k-space filter is {kind!r}; allowed: {', '.join(KSPACE_FILTERS)}")
    u = (np.arange(n) - n // 2) / (n / 2.0)  # -1 .. 1
    if kind == "hamming":
        return 0.54 + 0.46 * np.cos(np.pi * u)
    if kind == "tukey":  # flat over the inner half, a cosine taper over the outer half
        a = 0.5
        w = np.ones(n)
        edge = np.abs(u) > 1.0 - a
        w[edge] = 0.5 * (1.0 + np.cos(np.pi * (np.abs(u[edge]) - (1.0 - a)) / a))
        return w
    return np.ones(n)


def _section_segments(V_S: np.ndarray, faces: np.ndarray, z_mm: float) -> np.ndarray:
    """The mesh's section by the plane z = ``z_mm`` of S: segments (K, 2, 2) of (x, y) end points."""
    d = V_S[:, 2] - z_mm
    d = np.where(d == 0.0, 1e-12, d)  # a vertex on the plane counts as above it
    pos = d[faces] > 0  # (F, 3)
    n_pos = pos.sum(axis=1)
    cut = faces[(n_pos == 1) | (n_pos == 2)]
    if len(cut) == 0:
        return np.zeros((0, 2, 2))
    p = d[cut] > 0
    # the lone vertex (the one whose side differs from the other two) and the two edges from it
    lone = np.where(p.sum(axis=1) == 1, np.argmax(p, axis=1), np.argmin(p, axis=1))
    rows = np.arange(len(cut))
    a = cut[rows, lone]
    b = cut[rows, (lone + 1) % 3]
    c = cut[rows, (lone + 2) % 3]

    def crossing(i, j):
        t = d[i] / (d[i] - d[j])
        return V_S[i, :2] + t[:, None] * (V_S[j, :2] - V_S[i, :2])

    return np.stack([crossing(a, b), crossing(a, c)], axis=1)


def _inside_section(segments: np.ndarray, x0: float, y0: float, h: float, shape) -> np.ndarray:
    """(rows, cols) bool: grid points (x0 + j h, y0 + i h) inside the closed section, by even-odd scanlines."""
    rows, cols = shape
    if len(segments) == 0:
        return np.zeros(shape, dtype=bool)
    (xa, ya), (xb, yb) = segments[:, 0].T, segments[:, 1].T
    lo, hi = np.minimum(ya, yb), np.maximum(ya, yb)
    i0 = np.clip(np.ceil((lo - y0) / h), 0, rows).astype(int)  # rows with lo <= y < hi
    i1 = np.clip(np.ceil((hi - y0) / h), 0, rows).astype(int)
    n = i1 - i0
    keep = n > 0
    seg = np.repeat(np.flatnonzero(keep), n[keep])
    row = np.repeat(i0[keep], n[keep]) + (np.arange(seg.size) - np.repeat(np.cumsum(n[keep]) - n[keep], n[keep]))
    y = y0 + row * h
    t = (y - ya[seg]) / (yb[seg] - ya[seg])
    x = xa[seg] + t * (xb[seg] - xa[seg])
    col = np.clip(np.ceil((x - x0) / h), 0, cols).astype(int)  # first grid point right of the crossing
    toggles = np.zeros((rows, cols + 1), dtype=np.int32)
    np.add.at(toggles, (row, col), 1)
    return (np.cumsum(toggles[:, :cols], axis=1) & 1).astype(bool)


def fluid_occupancy(vertices_F_mm: np.ndarray, faces: np.ndarray, body: Body, T_F_from_S: np.ndarray,
                    x_mm: np.ndarray, y_mm: np.ndarray, z_mm: float) -> np.ndarray:
    """(len(y_mm), len(x_mm)) bool: fluid at the grid points (x, y, ``z_mm``) of S.

    ``vertices_F_mm`` (V, 3) and ``faces`` (F, 3): the body mesh in F;
    ``x_mm``, ``y_mm`` evenly spaced with one step. Fluid is the wall annulus
    of ``body`` (its analytic radii, ``WALL_MARGIN_MM`` inside) minus the mesh.
    """
    h = float(x_mm[1] - x_mm[0])
    V_S = apply(invert(T_F_from_S), vertices_F_mm)
    segs = _section_segments(V_S, faces, z_mm)
    out = np.zeros((len(y_mm), len(x_mm)), dtype=bool)
    if len(segs) == 0:
        return out
    # the section's bounding box: the channels are holes inside it
    j0 = max(0, int(np.floor((segs[..., 0].min() - x_mm[0]) / h)) - 1)
    j1 = min(len(x_mm), int(np.ceil((segs[..., 0].max() - x_mm[0]) / h)) + 2)
    i0 = max(0, int(np.floor((segs[..., 1].min() - y_mm[0]) / h)) - 1)
    i1 = min(len(y_mm), int(np.ceil((segs[..., 1].max() - y_mm[0]) / h)) + 2)
    if j1 <= j0 or i1 <= i0:
        return out
    xs, ys = x_mm[j0:j1], y_mm[i0:i1]
    body_in = _inside_section(segs, float(xs[0]), float(ys[0]), h, (len(ys), len(xs)))
    R, t = T_F_from_S[:3, :3], T_F_from_S[:3, 3]
    X, Y = xs[None, :], ys[:, None]
    px = R[0, 0] * X + R[0, 1] * Y + (R[0, 2] * z_mm + t[0])
    py = R[1, 0] * X + R[1, 1] * Y + (R[1, 2] * z_mm + t[1])
    pz = R[2, 0] * X + R[2, 1] * Y + (R[2, 2] * z_mm + t[2])
    r = np.hypot(px, py)
    wall = ((r > 0.5 * body.inner_diameter + WALL_MARGIN_MM) & (r < 0.5 * body.outer_diameter - WALL_MARGIN_MM)
            & (pz > 0.0) & (pz < body.length))
    out[i0:i1, j0:j1] = wall & ~body_in
    return out


def slice_placement(depth_mm: float, tilt_deg: float, azimuth_deg: float = 0.0, twist_deg: float = 0.0, *,
                    matrix: int = 256, pixel_mm: float = 0.5, thickness_mm: float = 2.0):
    """An axial slice (zero pixels, centred on the scanner origin) and the fiducial pose (4x4) that puts the
    slice at (depth, tilt, azimuth, twist) of :func:`~chic_register.model.pose.slice_frame` through F, the
    fiducial axis crossing the image centre. Returns ``(slice, T_scanner_from_fiducial)``."""
    n = int(matrix)
    origin = -np.array([(n - 1) / 2.0 * pixel_mm, (n - 1) / 2.0 * pixel_mm, 0.0])
    sl = Slice(np.zeros((n, n)), (pixel_mm, pixel_mm), origin, slice_thickness_mm=float(thickness_mm),
               source="<kspace>", modality="MR")
    T_image_from_S = rigid(np.eye(3), ((n - 1) / 2.0 * pixel_mm, (n - 1) / 2.0 * pixel_mm, 0.0))
    T_scanner_from_fiducial = sl.T_scanner_from_image() @ T_image_from_S @ invert(
        slice_frame(depth_mm, tilt_deg, azimuth_deg, twist_deg))
    return sl, T_scanner_from_fiducial


def kspace_image(vertices_F_mm: np.ndarray, faces: np.ndarray, body: Body, T_scanner_from_fiducial: np.ndarray,
                 placement: Slice, *, thickness_mm: float | None = None, oversample: int = 8, n_planes: int = 24,
                 kspace_filter: str = "none") -> np.ndarray:
    """The noise-free complex image (rows, cols) of the fluid in the body mesh (``vertices_F_mm`` (V, 3),
    ``faces`` (F, 3), in F) at pose ``T_scanner_from_fiducial``, on the grid of ``placement`` (its pixels'
    shape is the acquired matrix, its spacing the pixel size); ``thickness_mm`` defaults to the placement's."""
    rows, cols = placement.shape
    rs, cs = (float(v) for v in placement.pixel_spacing_mm)
    if rs != cs:
        raise ValueError(f"square pixels only, got spacing {placement.pixel_spacing_mm}")
    thk = float(placement.slice_thickness_mm if thickness_mm is None else thickness_mm)
    if not thk > 0:
        raise ValueError(f"slice thickness must be > 0, got {thk}")
    q = int(oversample)
    h = cs / q
    # image frame of the placement (origin at pixel (0, 0)): fine sample (m, n) at (n h, m h), pixel (i, j) at m = q i
    T_F_from_image = invert(np.asarray(T_scanner_from_fiducial, float)) @ placement.T_scanner_from_image()
    x_mm, y_mm = np.arange(q * cols) * h, np.arange(q * rows) * h
    V = np.asarray(vertices_F_mm, float)
    F = np.asarray(faces, np.int64)
    fine = np.zeros((q * rows, q * cols))
    for z, w in zip(*slice_profile(thk, n_planes)):
        fine += w * fluid_occupancy(V, F, body, T_F_from_image, x_mm, y_mm, float(z))
    spectrum = np.fft.fftshift(np.fft.fft2(fine))
    r0, c0 = (q * rows) // 2 - rows // 2, (q * cols) // 2 - cols // 2
    k = spectrum[r0:r0 + rows, c0:c0 + cols] / (q * q)
    k = k * kspace_window(rows, kspace_filter)[:, None] * kspace_window(cols, kspace_filter)[None, :]
    return np.fft.ifft2(np.fft.ifftshift(k))


def with_noise(image: np.ndarray, placement: Slice, snr: float | None, rng=None,
               thickness_mm: float | None = None) -> Slice:
    """The magnitude slice of a complex ``image`` (rows, cols) plus complex Gaussian noise of sigma 1 / ``snr``
    (None: no noise), placed as ``placement``."""
    if snr is not None:
        if not (snr > 0 and math.isfinite(snr)):
            raise ValueError(f"snr must be > 0, got {snr}")
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        s = 1.0 / float(snr)
        image = image + rng.normal(0.0, s, image.shape) + 1j * rng.normal(0.0, s, image.shape)
    thk = float(placement.slice_thickness_mm if thickness_mm is None else thickness_mm)
    return Slice(np.abs(image), placement.pixel_spacing_mm, placement.origin_mm, placement.col_dir,
                 placement.row_dir, thk, "<kspace>", modality="MR")


def kspace_slice(vertices_F_mm: np.ndarray, faces: np.ndarray, body: Body, T_scanner_from_fiducial: np.ndarray,
                 placement: Slice, *, snr: float | None = 20.0, thickness_mm: float | None = None,
                 oversample: int = 8, n_planes: int = 24, kspace_filter: str = "none",
                 rng=None) -> KSpaceSlice:
    """:func:`kspace_image` with Rician noise at ``snr`` (:func:`with_noise`): a slice ready for ``register``."""
    image = kspace_image(vertices_F_mm, faces, body, T_scanner_from_fiducial, placement, thickness_mm=thickness_mm,
                         oversample=oversample, n_planes=n_planes, kspace_filter=kspace_filter)
    return KSpaceSlice(with_noise(image, placement, snr, rng, thickness_mm),
                       np.asarray(T_scanner_from_fiducial, float))
