"""Several slices, one pose: the order slices are solved in, tracking a found pose, and the joint fit.

:func:`joint_fit` fits every slice's correspondences at once and, for a
volume's slices, drops those that disagree; :func:`track_pose` starts a slice
from a pose another slice found; :func:`no_slice_locked` sums up why none
locked.
"""

from __future__ import annotations

import math
import re

import numpy as np

from chic_register.detect.detected import DetectedSlice
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.refine import Fit, match_gate_mm, refine, reject_outliers
from chic_register.model.slices import Slice
from chic_register.model.tube_model import TubeModel, plane_crossings, poses_distinct
from chic_register.options import SolveOptions
from chic_register.verify.trust import check_trust


def solve_order(xys: list, model: TubeModel, skip_failed: bool) -> list[int]:
    """The order slices are solved in: as given, or (skipping) those with about one blob per tube first."""
    if not skip_failed:
        return list(range(len(xys)))
    K = len(model.ids)
    return sorted(range(len(xys)), key=lambda j: (abs(xys[j].shape[0] - K), j))


def track_pose(model: TubeModel, xy: np.ndarray, S: np.ndarray, T_F_from_scanner: np.ndarray, sl: Slice,
           opts: SolveOptions, res_mm: float):
    """A slice's fit refined from a pose found in another slice of the same volume, if trustworthy; else None."""
    gate = match_gate_mm(model, res_mm)
    fit = refine(model, [xy], [S], T_F_from_scanner, gates_mm=(gate, 0.6 * gate), iters_per_gate=3, final_iters=2)
    fit = reject_outliers(model, [xy], [S], fit, [res_mm], opts)
    try:
        check_trust(fit, [], model, [sl], opts, [S], [res_mm])
    except NoLock:
        return None
    return fit


def _decide(model: TubeModel, first, others, opts: SolveOptions, res_mm) -> "object":
    """The best of joint fits refined from several starts; :class:`AmbiguousFit` when a distinct one matches as
    many tubes within ``ambiguity_ratio`` of its RMS (the same rule as one slice's, over the whole series)."""
    fits = sorted([first, *others], key=lambda f: (-f.n_matched, f.rms_mm))
    best = fits[0]
    for other in fits[1:]:
        if (other.n_matched >= best.n_matched and other.rms_mm <= opts.ambiguity_ratio * max(best.rms_mm, 1e-3)
                and other.rms_mm <= opts.max_rms_px * min(res_mm)
                and poses_distinct(best.T_F_from_scanner, other.T_F_from_scanner, model)):
            raise AmbiguousFit(f"ambiguous fit: the slices together fit two distinct poses, matching {best.n_matched} "
                               f"and {other.n_matched} tubes with RMS {best.rms_mm:.3f} and {other.rms_mm:.3f} mm"
                               + ("" if opts.prior is not None else "; an approximate orientation (prior, --prior) "
                                  "picks one"), {"n_tubes": best.n_matched})
    return best


def joint_fit(model: TubeModel, seen: list[DetectedSlice], own_fits: list[Fit], opts: SolveOptions,
              skip_failed: bool, starts=()):
    """The joint fit of every slice's correspondences; ``(fit, dropped)``.

    Without ``skip_failed`` any disagreement is :class:`NoLock`. With it, a
    slice whose residual under the joint pose breaks its trust thresholds, or
    that matches fewer tubes than it did alone, is dropped (the worst first,
    then refit) and returned in ``dropped`` as ``(index, reason, RMS mm)``;
    ``fit`` then covers the remaining slices, in their order. ``starts``:
    more starting poses (the distinct fits of slices that alone were
    ambiguous); each is refined on all slices, and the series must single
    one out (:func:`_decide`). ``own_fits``: each slice's fit alone.
    """
    slices, xys = [d.slice for d in seen], [d.xy_mm for d in seen]
    Ss, res_mm = [d.T_scanner_from_image for d in seen], [d.resolution_mm for d in seen]
    start = min(own_fits, key=lambda f: f.rms_mm).T_F_from_scanner
    active = list(range(len(slices)))
    dropped = []
    while True:
        gate = max(model.diameter_mm.max(), 2 * max(res_mm[j] for j in active))
        sub = [xys[j] for j in active], [Ss[j] for j in active]
        best = refine(model, sub[0], sub[1], start, gates_mm=(gate, 0.6 * gate))
        if starts and not skip_failed:
            best = _decide(model, best, [refine(model, sub[0], sub[1], T, gates_mm=(gate, 0.6 * gate))
                                         for T in starts], opts, res_mm)
        if not skip_failed:
            check_trust(best, [], model, slices, opts, Ss, res_mm)
            if best.n_matched < sum(f.n_matched for f in own_fits):
                raise NoLock("the slices disagree: the joint pose matches fewer tubes than the slices alone",
                             {"n_tubes": best.n_matched})
            return best, dropped
        worst, why, worst_score = None, "", 1.0
        for n, j in enumerate(active):
            a, r = best.assignments[n], best.residuals[n]
            rms = math.sqrt(float(np.mean(r[a >= 0] ** 2))) if (a >= 0).any() else math.inf
            score = rms / (opts.max_rms_px * res_mm[j])
            if (a >= 0).sum() < own_fits[j].n_matched:
                score, reason = max(score, 1.0 + 1e-9) + 10.0, (
                    f"disagrees with the other slices: {int((a >= 0).sum())} tubes matched under the joint pose, "
                    f"{own_fits[j].n_matched} alone")
            else:
                reason = (f"disagrees with the other slices: residual RMS {rms:.3f} mm under the joint pose "
                          f"(limit {opts.max_rms_px * res_mm[j]:.3f} mm)")
            if score > worst_score:
                worst, why, worst_score = n, reason, score
        if worst is None or len(active) == 1:
            check_trust(best, [], model, [slices[j] for j in active], opts, [Ss[j] for j in active],
                         [res_mm[j] for j in active])
            return best, dropped
        j = active[worst]
        own = own_fits[j].assignments[0]  # the slice's own correspondences, at the joint pose
        q = plane_crossings(model, best.T_F_from_scanner @ Ss[j], margin_mm=5.0)[0]
        k = np.flatnonzero(own >= 0)
        rms = math.sqrt(float(np.mean(np.sum((q[k] - xys[j][own[k]]) ** 2, axis=1)))) if k.size else float("nan")
        if "tubes matched" in why:
            why += f"; its own tubes are {rms:.3f} mm RMS from the joint pose's crossings"
        dropped.append((j, why, rms))
        active.pop(worst)
        start = best.T_F_from_scanner


def no_slice_locked(skipped: list) -> str:
    """One line for slices of which none locked: how many, the commonest reasons, and one in full."""
    groups: dict[str, list] = {}
    for s in skipped:
        key = re.sub(r"\d+(\.\d+)?", "N", s.reason.split(":")[0]).strip()
        groups.setdefault(key, []).append(s)
    common = sorted(groups.items(), key=lambda kv: -len(kv[1]))
    head = common[0][1][len(common[0][1]) // 2]
    return (f"no slice of {len(skipped)} locked (" + "; ".join(f"{len(v)}x {k}" for k, v in common[:3])
            + f"); e.g. {head.source}: {head.reason}")
