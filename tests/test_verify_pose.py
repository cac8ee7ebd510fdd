"""A verified pose or none: reported false locks, the image checks, and a short seeded hunt."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from chic_register.errors import NoLock
from chic_register.imaging.render import render_tubes
from chic_register.imaging.simulate import add_rician_noise, simulate_slice
from chic_register.model.envelope import plane_status
from chic_register.model.pose import invert, slice_frame
from chic_register.model.slices import Slice
from chic_register.model.tubes import LineTube
from chic_register.pipeline.register import register

ROOT = Path(__file__).resolve().parents[1]


def _hunt():
    spec = importlib.util.spec_from_file_location("hunt", ROOT / "benchmarks" / "hunt.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["hunt"] = mod  # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


hunt = _hunt()


def _run_hunt_case(index: int, seed: int = 0) -> dict:
    """The hunt's judged outcome of one of its cases (benchmarks/hunt.py --seed SEED --case INDEX)."""
    geoms = hunt.load_geometries()
    return hunt.run_case(hunt.make_case(index, seed, geoms), geoms)


def _sim(geom, depth, tilt, az, tw, px=0.5, size=256, thick=2.0, noise="none", snr=20.0, seed=None, **kw):
    return simulate_slice(geom, depth, tilt, az, tw, shape=(size, size), pixel_spacing_mm=(px, px),
                          slice_thickness_mm=thick, noise=noise, snr=snr, image_position=(0.0, 0.0, 0.0),
                          rng=np.random.default_rng(seed), **kw)


def _outcome(geom, sim, pixels=None, spacing=None):
    """'no_lock' or the (TRE mm, rotation deg) of the pose reported ok."""
    sl = Slice(sim.slice.pixels if pixels is None else pixels, spacing or sim.truth.pixel_spacing_mm,
               slice_thickness_mm=sim.truth.slice_thickness_mm, source="case")
    try:
        reg = register([sl], geom)
    except NoLock as exc:
        assert exc.reason  # always a reason
        return "no_lock"
    return hunt.pose_error(reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial, geom.body.length)


def _zeroed(sim, share=0.3, seed=1):
    px = np.array(sim.slice.pixels)
    px[np.random.default_rng(seed).random(px.shape) < share] = 0.0
    return px


# six reported false locks (geometry exports/neuro, solved with --pixel-spacing 0.5 0.5 as reported,
# and with the slice's own spacing where that differs)
REPRODUCERS = {
    "A": dict(depth=48, tilt=17, az=-122, tw=-94, thick=1),
    "B": dict(depth=13.3636, tilt=46.2461, az=-6.9811, tw=96.2527, px=0.5, size=220, thick=0),
    "C": dict(depth=7.5425, tilt=40.1629, az=-24.4573, tw=-60.2909, px=0.7, size=157, thick=3, noise="rician",
              snr=27.47, seed=0),
    "D": dict(depth=1, tilt=0, az=0, tw=0, noise="rician", snr=20, seed=3),
    "E": dict(depth=25, tilt=0, az=0, tw=0),
    "F": dict(depth=25, tilt=0, az=0, tw=0, noise="rician", snr=20, seed=0),
}


@pytest.mark.parametrize("name", sorted(REPRODUCERS))
def test_issue_12_reproducers_give_no_lock_or_the_right_pose(neuro_geometry, name):
    kw = REPRODUCERS[name]
    sim = _sim(neuro_geometry, kw.pop("depth"), kw.pop("tilt"), kw.pop("az"), kw.pop("tw"), **kw)
    pixels = _zeroed(sim) if name == "F" else None
    spacings = [(0.5, 0.55)] if name == "E" else sorted({(0.5, 0.5), tuple(sim.truth.pixel_spacing_mm)})
    for spacing in spacings:
        out = _outcome(neuro_geometry, sim, pixels, spacing)
        if name == "E" or spacing != tuple(sim.truth.pixel_spacing_mm):
            assert out == "no_lock", (name, spacing, out)  # a wrong pixel spacing: no pose is right
        elif out != "no_lock":
            assert out[0] <= 0.5 and out[1] <= 0.5, (name, out)


def test_a_precise_slice_in_the_envelope_locks_and_verifies(neuro_geometry):
    sim = _sim(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=40, seed=5)
    assert plane_status(neuro_geometry, 25, 30, 40, 0.5, 2.0).twice == ()
    tre, rot = _outcome(neuro_geometry, sim)
    assert tre < 0.2 and rot < 0.3


def _circle_blob_slice(neuro_geometry, missing=()):
    """A slice (25, 30, 40, 10) with tube-sized fluid where the plane meets the circle of tube centres."""
    T = slice_frame(25, 30, 40, 10)
    sim = _sim(neuro_geometry, 25, 30, 40, 10, missing_tubes=missing)
    n = T[:3, 2]
    th = math.radians(160.0)  # between H1 (~150 deg here) and D2 (180), clear of both
    R = 12.5
    z = (n @ T[:3, 3] - R * (n[0] * math.cos(th) + n[1] * math.sin(th))) / n[2]
    p = np.array([R * math.cos(th), R * math.sin(th), z])
    blob = LineTube("blob", "other", tuple(p - 1.5 * n), tuple(p + 1.5 * n), 3.0)
    img = np.maximum(sim.slice.pixels, render_tubes([blob], T, (256, 256), (0.5, 0.5), 2.0, sim.truth.center_px))
    return sim, add_rician_noise(img, 40, np.random.default_rng(2))


def test_a_blob_on_the_tube_circle_that_no_pose_uses_is_left_alone(neuro_geometry, monkeypatch):
    """Tube-sized fluid on the circle of tube centres: the slice is solved again without each matched blob (the
    rivals that might use it); none explains the pixels, so the pose stands, right."""
    import chic_register.verify.rivals as rv

    calls = []
    real = rv.stray_rivals
    monkeypatch.setattr(rv, "stray_rivals", lambda *a: calls.append(1) or real(*a))
    sim, img = _circle_blob_slice(neuro_geometry)
    tre, rot = _outcome(neuro_geometry, sim, img)
    assert calls  # the stray was seen and its rivals tried
    assert tre <= 0.5 and rot <= 0.5


def test_a_blob_on_the_tube_circle_beside_a_missing_tube_is_refused(neuro_geometry):
    """A stray on the circle and a predicted tube missing: the signature of a wrong pose, whatever the fit says."""
    sim, img = _circle_blob_slice(neuro_geometry, missing=("O0",))
    with pytest.raises(NoLock, match="tubes' circle"):
        register([Slice(img, (0.5, 0.5), slice_thickness_mm=2.0, source="blob")], neuro_geometry)


@pytest.mark.parametrize("spacing", [(0.5, 0.56), (0.56, 0.5), (0.45, 0.5)])
def test_a_wrong_pixel_spacing_is_refused(neuro_geometry, spacing):
    sim = _sim(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=40, seed=5)
    assert _outcome(neuro_geometry, sim, spacing=spacing) == "no_lock"


@pytest.mark.parametrize("tilt, declared, axis", [(0, (0.53, 0.5), "rows"), (30, (0.5, 0.53), "columns")])
def test_a_stretch_the_pose_absorbs_is_seen_in_the_positions(neuro_geometry, tilt, declared, axis):
    """A 6 % spacing error that a tilted pose fits to 0.1 px (the section aspect cannot see it) is named by the
    positions' stretch test, along the right axis; the same slice with its true spacing does not trigger it."""
    sim = _sim(neuro_geometry, 25, tilt, 40, 10, noise="rician", snr=20, seed=5)
    with pytest.raises(NoLock, match=f"stretched -\\d+\\.\\d % along its {axis}") as info:
        register([Slice(sim.slice.pixels, declared, slice_thickness_mm=2.0, source="stretched")], neuro_geometry)
    assert info.value.detail["stretch_p"] < 1e-3
    right = Slice(sim.slice.pixels, (0.5, 0.5), slice_thickness_mm=2.0, source="right")
    try:
        register([right], neuro_geometry)
    except NoLock as exc:
        assert "stretched" not in exc.reason


def test_hunt_case_223_wrong_spacing_at_high_tilt_is_refused():
    """The last false lock of the 5000-case hunt (seed 0): a 12.6 % row-spacing error at 58.5 deg tilt, which the
    section fit would lock 5.4 mm off with a 0.05 mm residual, is refused by the stretch test."""
    out = _run_hunt_case(223)
    assert out["outcome"] == "no_lock" and "stretched" in out["reason"], out


def test_a_section_pulled_off_alone_is_left_out_and_the_pose_refitted(neuro_geometry):
    """Hand-made section measurements at the true crossings, one moved 0.3 mm against a 0.01 mm noise: that tube is
    left out and the refit lands on the truth; with every section where it belongs, none is."""
    from chic_register.fit.accuracy import drop_section_outliers
    from chic_register.fit.refine import refine
    from chic_register.model.tube_model import plane_crossings, prepare_geometry
    from chic_register.options import SolveOptions

    model = prepare_geometry(neuro_geometry)[0]
    T_F_from_S = slice_frame(20.0, 25.0, 40.0, 10.0)
    q, _, _, inside = plane_crossings(model, T_F_from_S)
    K = len(model.ids)
    xy = q[:, :2].copy()
    L = np.repeat(np.eye(2)[None] / 0.01, K, axis=0)  # 0.01 mm sigma in x and y
    rng = np.random.default_rng(3)
    xy += rng.normal(0.0, 0.01, xy.shape)
    moved = 4
    xy[moved] += (0.3, 0.0)
    S = np.eye(4)
    assign = [np.where(inside, np.arange(K), -1)]
    fit = refine(model, [xy], [S], T_F_from_S, gates_mm=(), final_iters=6, assign0=assign, strict_ends=False,
                 weights=[L])
    fit = dataclasses.replace(fit, measurements=[(xy, L, 0.01)])
    out = drop_section_outliers(model, fit, [S], SolveOptions())
    assert out is not fit and out.assignments[0][moved] == -1 and out.n_matched == fit.n_matched - 1
    _, rot_before = hunt.pose_error(invert(fit.T_F_from_scanner), invert(T_F_from_S), model.length_mm)
    _, rot_after = hunt.pose_error(invert(out.T_F_from_scanner), invert(T_F_from_S), model.length_mm)
    assert rot_after < 0.5 * rot_before
    xy[moved] -= (0.3, 0.0)
    clean = refine(model, [xy], [S], T_F_from_S, gates_mm=(), final_iters=6, assign0=assign, strict_ends=False,
                   weights=[L])
    clean = dataclasses.replace(clean, measurements=[(xy, L, 0.01)])
    assert drop_section_outliers(model, clean, [S], SolveOptions()) is clean


@pytest.mark.parametrize("case, locks", [(2522, True), (1795, False), (2706, True), (945, False)])
def test_hunt_cases_with_one_section_pulled_off(case, locks):
    """Hunt seed 0: case 2522 (a blob on the tubes' circle over O0, 26 deg tilt) locks on the other eight sections
    rather than being refused as imprecise; case 1795 (a tool in the bore, a near-normal needle-guide slice) would lock
    0.99 deg off without its pulled section at 3 sigma, and the stricter precision after a drop refuses it.
    Case 2706 (a blob on the circle matched in a tube's place): the whole fit leans towards it, every section's
    residual is raised (56-1956) and none is ten times the others'; against the pose refitted without it, it is,
    and the slice locks 0.06 deg off. Case 945 (stripes over several sections at 7 deg tilt): the largest residual
    is not alone, none is dropped and the slice stays refused (dropping the two that best cleaned the rest locked
    it 0.53 deg off)."""
    out = _run_hunt_case(case)
    if locks:
        assert out["outcome"] == "ok" and out["rot_deg"] < 0.1, out
    else:
        assert out["outcome"] == "no_lock", out


def test_plane_status_is_the_design_checks_on_one_plane(neuro_geometry):
    ok = plane_status(neuro_geometry, 25, 0, 0, 0.5, 2.0)
    assert ok.ok and ok.failure == "" and not ok.merged and not ok.outside
    # at depth 1 mm, tilt 0 each helix sits 11.4 deg from its diametric tube: 2.5 mm apart, 3 mm tubes overlap
    end = plane_status(neuro_geometry, 1, 0, 0, 0.5, 2.0)
    assert set(end.merged) == {("H0", "D0"), ("H1", "D1"), ("H2", "D2")}
    # a plane tilted through the top face misses tubes
    cut = plane_status(neuro_geometry, 48, 17, -122, 0.5, 1.0)
    assert not cut.ok and cut.failure == "tube_outside_body" and len(cut.outside) >= 1


def test_short_seeded_hunt_has_no_false_lock_and_no_crash():
    """~10 s: 40 random damaged slices of both designs (benchmarks/hunt.py, seed 12)."""
    results = hunt.hunt(40, seed=12, workers=1)
    s = hunt.summarise(results)["all"]
    bad = [r for r in results if r["outcome"] in ("false_lock", "crash", "setup_error")]
    assert not bad, bad
    assert s["ok"] >= 1  # the hunt is not vacuous: some slices lock (and are checked against the truth)


def test_wide_blobs_are_verified_with_a_fitted_point_spread(monkeypatch):
    """Z-frame rods drawn 2.5x as wide as the file says (point spread, as real images show them) are refused by the
    sharp model's shape test; the verification then fits a Gaussian point spread and the blurred model explains
    the pixels: the pose locks within 0.3 mm. Without the point-spread fit the same slice is refused."""
    import chic_register.verify.pixels as vp
    from chic_design.families import family_of
    from chic_design.spec import load_spec

    spec = load_spec(ROOT / "designs" / "zframe.yaml")
    zf = family_of(spec).geometry(spec)
    sim = simulate_slice(zf, 30, 15, 30, 0, noise="rician", snr=20, blob_width=2.5, rng=np.random.default_rng(1))
    sl, T_true = sim.slice, sim.truth.T_scanner_from_fiducial
    seen = []
    real = vp.verify_slice
    monkeypatch.setattr(vp, "verify_slice", lambda *a, **k: seen.append(real(*a, **k)) or seen[-1])
    reg = register([sl], zf, prior=T_true, trust_rot_deg=1.0)
    centre = np.array([0.0, 0.0, zf.body.length / 2, 1.0])
    assert np.linalg.norm((reg.T_scanner_from_fiducial - T_true) @ centre) < 0.3
    rod_radius_px = 0.5 * zf.tubes[0].diameter / float(max(sl.pixel_spacing_mm))
    assert seen and 0.5 * rod_radius_px < seen[-1].psf_px < 2.5 * rod_radius_px  # a 2.5x blob: sigma ~1.2 radii
    monkeypatch.setattr(vp, "PSF_SIGMAS_RADII", ())
    with pytest.raises(NoLock, match="shape and place"):
        register([sl], zf, prior=T_true, trust_rot_deg=1.0)


def test_window_least_squares_are_numpys():
    """The windows' least squares skip np.linalg.lstsq's wrapper: the same coefficients and rank, bit for bit, for
    full-rank, collinear and empty columns, and its answer where the call gives no finite one (NaN pixels)."""
    from chic_register.util.lapack import lstsq as _lstsq

    rng = np.random.default_rng(0)
    for i in range(300):
        m, n = int(rng.integers(1, 300)), int(rng.integers(1, 4))
        A, y = rng.normal(size=(m, n)), rng.normal(size=m)
        if i % 3 == 1 and n > 1:
            A[:, 1] = 2.0 * A[:, 0]
        if i % 5 == 2:
            A[:, -1] = 0.0
        coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
        got, got_rank = _lstsq(A, y)
        np.testing.assert_array_equal(got, coef)
        assert got_rank == rank
    y[0] = np.nan
    np.testing.assert_array_equal(_lstsq(A, y)[0], np.linalg.lstsq(A, y, rcond=None)[0])


def test_aspect_standard_error_matches_the_scatter_of_noisy_sections():
    """A tilted section's spread aspect (column over row, :func:`window_spread`) measured in 2000 noisy draws scatters as
    :func:`aspect_error` predicts from the pixel noise (within 15 %), at a low and a moderate SNR."""
    from chic_register.verify.windows import aspect_error, window_spread

    r, c = np.mgrid[0:15, 0:19].astype(float)
    section = np.clip(1.0 - np.hypot((r - 7.0) / 3.0, (c - 9.0) / 4.5), 0.0, 0.3) / 0.3  # an ellipse, 3 x 4.5 px
    support = section > 0.0
    rng = np.random.default_rng(4)
    for sigma in (0.12, 0.04):
        aspects, predicted = [], []
        for _ in range(2000):
            w = (section + rng.normal(0.0, sigma, section.shape)) * support
            v = window_spread(w)
            aspects.append(math.sqrt(v[1] / v[0]))
            predicted.append(aspect_error(w, support, v, sigma))
        rel = np.std(aspects) / np.mean(aspects)
        assert abs(np.median(predicted) / rel - 1.0) < 0.15, (sigma, rel, np.median(predicted))


@pytest.mark.parametrize("case", [1088, 3546])
def test_hunt_low_snr_sections_with_the_right_spacing_are_not_called_stretched(case):
    """Hunt seed 0, low SNR (7.6 and 9.6) at 54-67 deg tilt: three tubes' aspects read 4-5 % off one by their noise
    alone (a per-tube standard error of 3-5 %); the spacing test's tolerance allows for that noise, and both lock."""
    out = _run_hunt_case(case)
    assert out["outcome"] == "ok" and out["rot_deg"] < 0.2, out


def test_a_rival_that_falls_back_onto_the_pose_under_the_section_fit_is_no_rival(monkeypatch):
    """Hunt seed 0, clean needle-guide slices 9 deg from normal: a rival 1.4 deg (case 3423) or 10 deg (case 3968)
    off, fitted to the blob centres only, explains the pixels within the 3 % model floor of the section-fitted
    pose; given the section fit too, it lands on the pose, so both lock on the truth. Without that refit both are
    refused as ambiguous. Case 4340 (its tilt mirrored: a rival 18 deg off that stays there and verifies) is
    refused all the same."""
    import chic_register.verify.rivals as rv

    for case in (3423, 3968):
        out = _run_hunt_case(case)
        assert out["outcome"] == "ok" and out["rot_deg"] < 0.1 and out["tre_mm"] < 0.05, out
    out = _run_hunt_case(4340)
    assert out["outcome"] == "no_lock" and "ambiguous" in out["reason"], out
    monkeypatch.setattr(rv, "falls_onto_pose", lambda *a: False)
    for case in (3423, 3968):
        out = _run_hunt_case(case)
        assert out["outcome"] == "no_lock" and "ambiguous" in out["reason"], out


def test_the_section_fit_that_moves_off_the_blob_fit_is_verified_at_a_stricter_precision():
    """Hunt seed 0, 10-40 % of the pixels zeroed: the blob centres put cases 269 and 767 1.9 and 1.0 deg off; the
    section fit moves 1-2 deg from there, onto the truth (0.05 and 0.11 deg). The section fit's pose is verified,
    at 4.5 sigma, and both lock. Seed 5 case 2175 (a thick slab beyond the envelope) would lock 1.49 deg off that
    way at 3 sigma and is refused at 4.5."""
    for case in (269, 767):
        out = _run_hunt_case(case)
        assert out["outcome"] == "ok" and out["rot_deg"] < 0.15 and out["tre_mm"] < 0.1, out
    out = _run_hunt_case(2175, 5)
    assert out["outcome"] == "no_lock" and "not precise enough" in out["reason"], out


def test_blob_level_ambiguity_is_left_to_the_pixels():
    """Hunt seed 0, cases 614 (a blob on the tubes' circle) and 4045 (zeroed pixels): two distinct poses fit the
    blob centres about as well; that alone is no refusal ("ambiguous fit"): the pixels tell them apart (the
    rival test), and both lock on the truth."""
    for case in (614, 4045):
        out = _run_hunt_case(case)
        assert out["outcome"] == "ok" and out["rot_deg"] < 0.1, out


def test_a_motion_ghost_of_the_whole_pattern_is_a_rival(monkeypatch):
    """Hunt seed 2, case 476: a motion ghost at 45 % repeats all nine sections 22 mm away and the first guess fits
    the ghost; the slice solved again on the blobs the pose leaves unmatched finds the real copy, which explains
    the pixels far better: refused as ambiguous, not locked 22 mm off. Without that rival it false-locks."""
    import chic_register.verify.rivals as rv

    out = _run_hunt_case(476, 2)
    assert out["outcome"] == "no_lock" and "ambiguous" in out["reason"], out
    monkeypatch.setattr(rv, "second_copy_rivals", lambda *a: [])
    assert _run_hunt_case(476, 2)["outcome"] == "false_lock"


def test_the_pose_is_never_more_precise_than_its_pixel_noise_allows(monkeypatch):
    """Hunt seed 2, case 146 (a ghosted needle-guide slice, 0.61 deg off): its nine residuals scatter at a third
    of their noise, so the scatter-based precision passed; the covariance from the pixel noise puts 3 sigma at
    0.82 deg and the pose is refused as imprecise. Without that test it false-locks."""
    import chic_register.pipeline.results as so

    out = _run_hunt_case(146, 2)
    assert out["outcome"] == "no_lock" and "predicted from the pixel noise" in out["reason"], out
    monkeypatch.setattr(so, "check_noise_precision", lambda *a: None)
    assert _run_hunt_case(146, 2)["outcome"] == "false_lock"


@pytest.mark.parametrize("spacing", [(0.5, 0.56), (0.45, 0.5)])
def test_a_wrong_pixel_spacing_is_refused_at_low_snr(neuro_geometry, spacing):
    sim = _sim(neuro_geometry, 25, 45, 40, 10, noise="rician", snr=8, seed=5)
    assert _outcome(neuro_geometry, sim, spacing=spacing) == "no_lock"


def test_an_isotropic_scale_is_named_with_the_spacing_that_registers_it(neuro_geometry):
    """A slice declared 1 % too coarse along both axes (as a print 1 % too large, or a gradient calibration off by
    that much, looks): refused as a scale of the whole image, naming the spacing that would register it; declared so, the
    slice locks on the true pose."""
    import re

    sim = _sim(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=30, seed=5)
    with pytest.raises(NoLock, match="scaled -\\d\\.\\d\\d % along both axes") as info:
        register([Slice(sim.slice.pixels, (0.505, 0.505), slice_thickness_mm=2.0, source="scaled")], neuro_geometry)
    assert "fiducial is that much larger than its geometry file says" in info.value.reason
    rs, cs = map(float, re.search(r"pixel spacing of (\S+) x (\S+) mm \(row, col\)", info.value.reason).groups())
    assert rs == pytest.approx(0.5, rel=0.003) and cs == pytest.approx(0.5, rel=0.003)
    reg = register([Slice(sim.slice.pixels, (rs, cs), slice_thickness_mm=2.0, source="rescaled")], neuro_geometry)
    tre, rot = hunt.pose_error(reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial, neuro_geometry.body.length)
    assert tre < 0.2 and rot < 0.3


def _hunt_print():
    spec = importlib.util.spec_from_file_location("hunt_print", ROOT / "benchmarks" / "hunt_print.py")
    hp = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec.loader.exec_module(hp)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return hp


@pytest.mark.parametrize("kind, cases", [("other_design", 12), ("water_bath", 12)])
def test_print_hunt_short(kind, cases):
    """benchmarks/hunt_print.py in-process: slices solved with the other design's geometry file never lock, and
    fiducials in a water bath lock without a false lock (seed 5; the full runs are in the README)."""
    hp = _hunt_print()
    hp._init(kind, 0.0)
    out = [hp.run_case(i, 5, kind, 0.0)["outcome"] for i in range(cases)]
    assert "crash" not in out and "false_lock" not in out, out
    if kind == "other_design":
        assert set(out) == {"no_lock"}
    else:
        assert "ok" in out


@pytest.mark.parametrize("case", [118, 136])
def test_a_fiducial_in_a_water_bath_is_found_on_the_flattened_image(case):
    """hunt_print water_bath, seed 5 (a needle guide and a neuro slice): the water is most of the image, so the
    detector's background mixes it with the dark plastic and its noise estimate is ten times the pixels' own; the
    flattened second look is taken on the neighbour differences' noise, finds the tubes, and the slice locks."""
    hp = _hunt_print()
    hp._init("water_bath", 0.0)
    out = hp.run_case(case, 5, "water_bath", 0.0)
    assert out["outcome"] == "ok" and out["rot_deg"] < 0.2, out


def test_difference_sigma_holds_beside_large_bright_regions():
    """Gaussian noise (sigma 2) over an image half of which is a bright slab: the neighbour-difference estimate is
    within 5 % of 2, where the pixels' own spread is twenty times that."""
    from chic_register.detect.noise import difference_sigma

    rng = np.random.default_rng(1)
    img = rng.normal(0.0, 2.0, (200, 200))
    img[:, 100:] += 80.0
    assert difference_sigma(img) == pytest.approx(2.0, rel=0.05)
    assert np.std(img) > 20.0
