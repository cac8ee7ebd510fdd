"""A volume's first guess from its voxels: the tube centrelines searched in 3-D.

When the blobs are much wider than the channels (1.5-2.5x: point spread,
partial volume, fluid around a printed channel), neighbouring sections merge
in every slice and no slice alone gives a first guess: its candidates are
too few, or their centroids too biased, for the slice's closed form. A
volume still shows every tube as a bright line or helix in 3-D. Here the
fiducial's axis comes from the principal directions of the bright voxels,
its centre from a circle fitted to them across the axis, and the twist about
the axis and the depth along it from a grid search of the mean brightness
along every tube centreline (the geometry file's tubes at the pose); each
of the best grid poses is then refined on all six degrees of freedom on the
same score. The outcome is only a start: the solver fits the pose to the
pixels (:mod:`chic_register.fit.blurred`) and verifies it.
"""

from __future__ import annotations

import numpy as np

from chic_register.model.pose import invert
from chic_register.model.tube_model import TubeModel, exp_se3, poses_distinct

#: Centreline samples this far apart (mm): the wide blobs this is for are several millimetres across.
SAMPLE_MM = 1.5
#: Grid steps of the twist (deg) and of the depth along the axis (mm).
TWIST_STEP_DEG, DEPTH_STEP_MM = 5.0, 2.0
#: Voxels brighter than the background by this share of the fluid's level count as fluid.
FLUID_SHARE = 0.4
#: Grid poses refined (the best distinct ones).
N_REFINED = 3


def _normalised(vox: np.ndarray) -> np.ndarray:
    """Voxels as ``(v - background) / (fluid - background)``: the median is the background, the 99.9th
    percentile the fluid."""
    v = np.asarray(vox, np.float32)
    flat = v.ravel()
    step = max(1, flat.size // 200_000)
    sample = np.sort(flat[::step])
    bg, hi = float(sample[sample.size // 2]), float(sample[int(0.999 * (sample.size - 1))])
    return (v - bg) / max(hi - bg, 1e-12)


def _lookup(vol: np.ndarray, ijk: np.ndarray, linear: bool) -> np.ndarray:
    """Values of ``vol`` (nk, nj, ni) at float indices ``ijk`` (..., 3) as (i, j, k); 0 outside."""
    nk, nj, ni = vol.shape
    if not linear:
        idx = np.rint(ijk).astype(np.int64)
        i, j, k = idx[..., 0], idx[..., 1], idx[..., 2]
        ok = (i >= 0) & (i < ni) & (j >= 0) & (j < nj) & (k >= 0) & (k < nk)
        flat = (np.clip(k, 0, nk - 1) * nj + np.clip(j, 0, nj - 1)) * ni + np.clip(i, 0, ni - 1)
        return np.where(ok, vol.ravel()[flat], 0.0)
    f = np.floor(ijk)
    w = ijk - f
    base = f.astype(np.int64)
    out = np.zeros(ijk.shape[:-1])
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                i, j, k = base[..., 0] + di, base[..., 1] + dj, base[..., 2] + dk
                ok = (i >= 0) & (i < ni) & (j >= 0) & (j < nj) & (k >= 0) & (k < nk)
                flat = (np.clip(k, 0, nk - 1) * nj + np.clip(j, 0, nj - 1)) * ni + np.clip(i, 0, ni - 1)
                wt = (w[..., 0] if di else 1 - w[..., 0]) * (w[..., 1] if dj else 1 - w[..., 1]) * \
                     (w[..., 2] if dk else 1 - w[..., 2])
                out += np.where(ok, wt * vol.ravel()[flat], 0.0)
    return out


def _centrelines(model: TubeModel):
    """Centreline samples of every tube in F (N, 3) and their weights (each tube's samples sum to 1 / K)."""
    pts, wts = [], []
    for tube in model.tubes:
        p = np.asarray(tube.sample(SAMPLE_MM), float)
        pts.append(p)
        wts.append(np.full(len(p), 1.0 / (len(p) * len(model.tubes))))
    return np.concatenate(pts), np.concatenate(wts)


def _frame_with_z(a: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit vector ``a``."""
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, a)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(a, x), a])


def _rot_z(deg) -> np.ndarray:
    """(n, 3, 3) rotations about z by each angle of ``deg``."""
    t = np.radians(np.atleast_1d(deg))
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((t.size, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _circle_centre(xy: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Centre of the weighted algebraic (Kasa) circle through the points ``xy`` (N, 2)."""
    A = np.column_stack([xy, np.ones(len(xy))]) * np.sqrt(w)[:, None]
    b = np.sum(xy * xy, axis=1) * np.sqrt(w)
    sol = np.linalg.lstsq(A, b, rcond=None)[0]
    return 0.5 * sol[:2]


def volume_first_guesses(voxels: np.ndarray, affine_lps: np.ndarray, model: TubeModel) -> list:
    """Poses ``(score, T_F_from_scanner)`` of the fiducial in a volume, best first, distinct from each other.

    ``voxels`` (nk, nj, ni), ``affine_lps``: voxel index (i, j, k, 1) to scanner mm. ``score``: the mean
    brightness along the tube centrelines, as a share of the fluid's level (about 1 on the fluid, 0 on the
    background). Empty when the volume shows nothing bright.
    """
    vol = _normalised(voxels)
    kk, jj, ii = np.nonzero(vol > FLUID_SHARE)
    if kk.size < 50:
        return []
    w = vol[kk, jj, ii] - FLUID_SHARE
    p = np.column_stack([ii, jj, kk]) @ affine_lps[:3, :3].T + affine_lps[:3, 3]
    mean = (w @ p) / w.sum()
    d = p - mean
    evals, evecs = np.linalg.eigh((d * w[:, None]).T @ d / w.sum())
    to_index = np.linalg.inv(affine_lps)
    P, wts = _centrelines(model)
    L = model.length_mm
    twists = np.arange(0.0, 360.0, TWIST_STEP_DEG)
    Rz = _rot_z(twists)
    grid, groups = [], []
    for axis in (evecs[:, 2], evecs[:, 0]):  # a long fiducial: the largest spread; a short piece of one: the least
        for sign in (1.0, -1.0):
            a = sign * axis
            R0 = _frame_with_z(a)
            local = d @ R0
            c = mean + R0[:, :2] @ _circle_centre(local[:, :2], w)
            s = local[:, 2]
            lo, hi = float(np.min(s)), float(np.max(s))
            z0s = np.arange(lo - L, hi + DEPTH_STEP_MM, DEPTH_STEP_MM)  # where F's origin sits along the axis
            rotated = np.einsum("tij,nj->tni", R0 @ Rz, P)  # (T, N, 3) scanner directions of the samples
            base = rotated[:, None] + (c + a[None, :] * (z0s[:, None] - 0.0))[None, :, None, :]  # (T, Z, N, 3)
            ijk = base @ to_index[:3, :3].T + to_index[:3, 3]
            score = _lookup(vol, ijk, linear=False) @ wts  # (T, Z)
            for t, z in zip(*np.unravel_index(np.argsort(score, axis=None)[::-1][:12], score.shape)):
                X = np.eye(4)
                X[:3, :3] = R0 @ Rz[t]
                X[:3, 3] = c + a * z0s[z]
                grid.append((float(score[t, z]), invert(X), len(groups)))
            groups.append(a)
    grid.sort(key=lambda sx: -sx[0])
    starts = []
    for s, X, _ in grid:
        if all(poses_distinct(X, Y, model) for _, Y in starts):
            starts.append((s, X))
        if len(starts) == N_REFINED:
            break
    for g in range(len(groups)):  # and each axis direction's best (a turned twin of the pose is one of them)
        s, X = next((s, X) for s, X, gi in grid if gi == g)
        if all(poses_distinct(X, Y, model) for _, Y in starts):
            starts.append((s, X))
    out = []
    for _, X in starts:
        s, Xr = _refine(vol, to_index, P, wts, X)
        if all(poses_distinct(Xr, Y, model) for _, Y in out):
            out.append((s, Xr))
    return sorted(out, key=lambda sx: -sx[0])


def _refine(vol, to_index, P, wts, X0):
    """The pose near ``X0`` (T_F_from_scanner) of the highest centreline score (trilinear), by Nelder-Mead over a
    scanner-frame twist (deg, mm) about the samples' mean."""
    from scipy.optimize import minimize  # deferred: loads scipy only when used (one-shot start-up)

    T0 = invert(X0)
    centre = T0[:3, :3] @ P.mean(axis=0) + T0[:3, 3]

    def pose(v):
        xi = np.concatenate([np.radians(v[:3]), v[3:]])
        C = np.eye(4)
        C[:3, 3] = centre
        Ci = np.eye(4)
        Ci[:3, 3] = -centre
        return C @ exp_se3(xi) @ Ci @ T0  # T_scanner_from_F moved

    def cost(v):
        T = pose(v)
        q = P @ T[:3, :3].T + T[:3, 3]
        return -float(_lookup(vol, q @ to_index[:3, :3].T + to_index[:3, 3], linear=True) @ wts)

    simplex = np.vstack([np.zeros(6), np.diag([3.0, 3.0, 3.0, 1.5, 1.5, 1.5])])
    res = minimize(cost, np.zeros(6), method="Nelder-Mead",
                   options={"initial_simplex": simplex, "xatol": 0.02, "fatol": 1e-5, "maxfev": 1500})
    return -float(res.fun), invert(pose(res.x))
