"""The peer of the project's Z-frame registration: 3D Slicer's ZFrameRegistration algorithm for the z001 frame.

Susil et al., "A single image registration method for CT-guided interventions" (MICCAI 1999), as ZFrameRegistration
applies it to the seven-rod z001 frame, written from the algorithm's description. Per axial slice:

1. the seven rods' intercepts: the slice correlated (FFT) with an 11 x 11 disc, the seven highest peaks taken one by
   one (a 21 x 21 neighbourhood suppressed after each), each refined by a 3-point parabola along rows and columns;
2. ordered around the frame: the four farthest from their bounding box's centre are the axial rods, each other one
   lies between two neighbouring corners, the pair with none between them is the open face (F's y = -30);
3. each diagonal's point in F from where it lies between its face's two rods (a ratio of image distances);
4. the pose from the triangle of the three diagonal points, in F and in the slice;
5. poses averaged over the slices: positions by their mean, orientations by the principal eigenvector of the sum of
   the quaternions' outer products.

A slice is skipped when fewer than seven good peaks stand out, they cannot be ordered, or the corners' opposite sides
are more than 5 deg from parallel. Poses are ``T_scanner_from_fiducial`` (scanner LPS mm) in the project's frame F
(z001's axes, origin on the axis in the bottom face), as :func:`chic_register.pipeline.volume.register_volume` gives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import fftconvolve
from scipy.spatial.transform import Rotation

from chic_register.io.volumes import Volume

KERNEL_PX = 11
SUPPRESS_PX = 21
N_RODS = 7
ON_SIDE = 1.05  # a point is between corners a and b when d(a, p) + d(p, b) < ON_SIDE * d(a, b)
MAX_SIDE_ANGLE_DEG = 5.0
#: A good peak's correlation stands this many robust standard deviations above the slice's median correlation
#: (what tells a rod from noise on the slices beyond the frame; the algorithm's own range is chosen by hand).
PEAK_SIGMAS = 6.0
#: The axial rods A0-A3 in F's counter-clockwise order seen from +z; the open face (no diagonal) runs from A3 to A0.
CORNERS_F = np.array([[30.0, -30.0], [30.0, 30.0], [-30.0, 30.0], [-30.0, -30.0]])
#: Each diagonal's ends in F, on the face from corner i to corner i + 1 (faces +x, +y, -x), starting at z = 0.
DIAGONALS_F = (
    (np.array([30.0, 30.0, 0.0]), np.array([30.0, -30.0, 60.0])),
    (np.array([-30.0, 30.0, 0.0]), np.array([30.0, 30.0, 60.0])),
    (np.array([-30.0, -30.0, 0.0]), np.array([-30.0, 30.0, 60.0])),
)


@dataclass(frozen=True)
class SliceResult:
    """One slice: its pose (None when skipped, with the reason), the peaks in image mm (x along columns, y along rows;
    ordered A0, D+x, A1, D+y, A2, D-x, A3 once ordering succeeded) and the diagonals' heights in F (mm)."""

    k: int
    T_scanner_from_fiducial: np.ndarray | None
    reason: str = ""
    points_mm: np.ndarray | None = None
    heights_mm: tuple[float, float, float] | None = None


def disc_kernel(size_px: int = KERNEL_PX) -> np.ndarray:
    """A disc filling a ``size_px`` square (ones inside radius size/2, zeros in the corners)."""
    r = np.arange(size_px) - (size_px - 1) / 2
    return (np.hypot(*np.meshgrid(r, r)) <= size_px / 2).astype(float)


def find_peaks(image: np.ndarray, n: int = N_RODS) -> tuple[np.ndarray, str]:
    """``(n x 2 (row, col), reason)``: the ``n`` highest peaks of the disc correlation, sub-pixel where the parabola
    allows; the reason is empty unless some peak is no good (too faint against the slice's correlation, on the
    edge, or no clear maximum: the slope of something larger than a rod)."""
    corr = fftconvolve(np.asarray(image, float), disc_kernel(), mode="same")  # the disc is symmetric: a correlation
    seen = corr[corr > 1e-9 * corr.max()]  # where the image has signal (a masked scan's zeros left out)
    if seen.size < corr.size // 10:
        return np.empty((0, 2)), "an empty slice"
    med = float(np.median(seen))
    level = med + PEAK_SIGMAS * 1.4826 * float(np.median(np.abs(seen - med)))
    work = corr.copy()
    h, w = corr.shape
    half = SUPPRESS_PX // 2
    out, reasons = [], []
    for _ in range(n):
        r, c = np.unravel_index(int(np.argmax(work)), work.shape)
        work[max(r - half, 0):r + half + 1, max(c - half, 0):c + half + 1] = -np.inf
        if corr[r, c] < level:
            reasons.append("a peak too faint to tell from noise")
        if not (0 < r < h - 1 and 0 < c < w - 1):
            reasons.append("a peak on the image's edge")
            out.append((r, c))
            continue
        offsets = []
        for lo, mid, hi in ((corr[r - 1, c], corr[r, c], corr[r + 1, c]), (corr[r, c - 1], corr[r, c], corr[r, c + 1])):
            curv = lo - 2 * mid + hi
            if curv < 0 and abs(lo - hi) <= -curv:  # a maximum: the parabola's vertex within half a pixel
                offsets.append(0.5 * (lo - hi) / curv)
            else:
                reasons.append("a peak that is no maximum")
                offsets.append(0.0)
        out.append((r + offsets[0], c + offsets[1]))
    return np.array(out, float), (reasons[0] if reasons else "")


def order_points(points_mm: np.ndarray, ccw: bool) -> tuple[np.ndarray | None, str]:
    """The seven intercepts (image mm) ordered A0, D+x, A1, D+y, A2, D-x, A3, or ``(None, reason)``.

    ``ccw``: F's counter-clockwise order (seen from +z) is counter-clockwise in the image's (x, y) too (the frame's
    z along the slice normal, not against it)."""
    lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
    centre = 0.5 * (lo + hi)
    far = np.argsort(-np.linalg.norm(points_mm - centre, axis=1))
    corners, others = points_mm[far[:4]], points_mm[far[4:]]
    d = corners - centre
    angle = np.arctan2(d[:, 1], d[:, 0])
    corners = corners[np.argsort(angle if ccw else -angle)]
    on_side = [None] * 4
    for p in others:
        sides = [i for i in range(4) if np.linalg.norm(corners[i] - p) + np.linalg.norm(p - corners[(i + 1) % 4])
                 < ON_SIDE * np.linalg.norm(corners[i] - corners[(i + 1) % 4])]
        if len(sides) != 1 or on_side[sides[0]] is not None:
            return None, "a point between no two corners (or two points between the same)"
        on_side[sides[0]] = p
    open_side = [i for i in range(4) if on_side[i] is None]
    first = (open_side[0] + 1) % 4  # the corner after the open face: A0
    ordered = []
    for i in range(4):
        ordered.append(corners[(first + i) % 4])
        if i < 3:
            ordered.append(on_side[(first + i) % 4])
    return np.array(ordered), ""


def sides_parallel(corners_mm: np.ndarray) -> bool:
    """The corner quadrilateral's opposite sides within :data:`MAX_SIDE_ANGLE_DEG` of parallel."""
    sides = np.roll(corners_mm, -1, axis=0) - corners_mm
    for a, b in ((sides[0], sides[2]), (sides[1], sides[3])):
        cos = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
        if math.degrees(math.acos(min(1.0, cos))) > MAX_SIDE_ANGLE_DEG:
            return False
    return True


def diagonal_points_F(ordered_mm: np.ndarray) -> np.ndarray:
    """(3, 3) the diagonals' points in F: each at the fraction of its face that it lies from its start rod."""
    corners = ordered_mm[0::2]
    out = []
    for face, (start, end) in enumerate(DIAGONALS_F):
        i0 = int(np.flatnonzero(np.all(CORNERS_F == start[:2], axis=1))[0])  # the rod the diagonal starts at
        i1 = int(np.flatnonzero(np.all(CORNERS_F == end[:2], axis=1))[0])
        p = ordered_mm[2 * face + 1]
        ratio = np.linalg.norm(p - corners[i0]) / np.linalg.norm(corners[i1] - corners[i0])
        out.append(start + ratio * (end - start))
    return np.array(out)


def triangle_frame(p: np.ndarray) -> np.ndarray:
    """3x3 orthonormal frame of a triangle (P2, P4, P6): x along P2 - P6, z normal to the triangle, y = z x x."""
    vx, vy = p[0] - p[2], p[1] - p[2]
    x = vx / np.linalg.norm(vx)
    z = np.cross(vx, vy)
    z /= np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z])


def triangle_pose(tri_F: np.ndarray, tri_image: np.ndarray) -> np.ndarray:
    """``T_image_from_F`` (4x4) carrying the frame triangle onto the image triangle: the rotation between their
    frames (``Q_image * conj(Q_frame)``), the translation between their centroids."""
    R = triangle_frame(tri_image) @ triangle_frame(tri_F).T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = tri_image.mean(axis=0) - R @ tri_F.mean(axis=0)
    return T


def average_poses(poses: list[np.ndarray]) -> np.ndarray:
    """Mean position; orientation the principal eigenvector of ``sum(q q^T)`` over the poses' quaternions."""
    q = Rotation.from_matrix(np.array([T[:3, :3] for T in poses])).as_quat()
    w, v = np.linalg.eigh(q.T @ q)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v[:, np.argmax(w)]).as_matrix()
    T[:3, 3] = np.mean([T_[:3, 3] for T_ in poses], axis=0)
    return T


def register_slice(volume: Volume, k: int, up_lps=(0.0, 0.0, 1.0)) -> SliceResult:
    """One native slice's pose, or the reason it is skipped; ``up_lps``: roughly F's +z in the scanner (the mount)."""
    sl = volume.native_slice(k)
    peaks, reason = find_peaks(sl.pixels)
    row_mm, col_mm = sl.pixel_spacing_mm
    points = np.column_stack([peaks[:, 1] * col_mm, peaks[:, 0] * row_mm])  # image (x, y) mm
    if reason:
        return SliceResult(k, None, reason, points)
    ordered, reason = order_points(points, ccw=float(np.dot(sl.normal, up_lps)) > 0)
    if ordered is None:
        return SliceResult(k, None, reason, points)
    if not sides_parallel(ordered[0::2]):
        return SliceResult(k, None, f"opposite sides more than {MAX_SIDE_ANGLE_DEG:g} deg from parallel", ordered)
    tri_F = diagonal_points_F(ordered)
    tri_image = np.column_stack([ordered[1::2], np.zeros(3)])
    T = sl.T_scanner_from_image() @ triangle_pose(tri_F, tri_image)
    return SliceResult(k, T, "", ordered, tuple(float(z) for z in tri_F[:, 2]))


def register_zframe_volume(volume: Volume, slices=None, up_lps=(0.0, 0.0, 1.0)):
    """``(T_scanner_from_fiducial 4x4 or None, [SliceResult])`` from ``slices`` (indices; default all), averaged over
    those that pass; ``up_lps`` is the scanner direction F's +z roughly points along (z001 on its mount: +S)."""
    ks = range(volume.shape[0]) if slices is None else slices
    info = [register_slice(volume, int(k), up_lps) for k in ks]
    poses = [r.T_scanner_from_fiducial for r in info if r.T_scanner_from_fiducial is not None]
    return (average_poses(poses) if poses else None), info
