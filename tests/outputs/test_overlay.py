"""The overlay of solve --overlay: labels that never collide, a true scale bar, a view cropped on the fiducial."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from chic_register.cli.inputs import load_prior
from chic_register.detect.blobs import detect_blobs
from chic_register.imaging.simulate import simulate_slice
from chic_register.io.volumes import read_volume
from chic_register.outputs.overlay import (
    LABEL_GID,
    SCALE_BAR_GID,
    SCALE_BAR_LABEL_GID,
    ZOOM_BOX_GID,
    draw_overlay,
    overlay_figure,
    predicted_crossings_rc,
    scale_bar_mm,
    view_bounds,
)
from chic_register.pipeline.register import register
from chic_register.pipeline.volume import register_volume
from tests.conftest import REAL

#: (depth, tilt, azimuth, twist): the README's slice (D3 and O0 side by side), a tilted and a steep one
POSES = [(22.0, 20.0, 30.0, 15.0), (12.0, 35.0, 60.0, -20.0), (30.0, 45.0, 200.0, 75.0)]


def _solved(geom, pose, **kw):
    sim = simulate_slice(geom, *pose, noise="rician", snr=20, distractors=3, bore_signal=0.6, rng=3, **kw)
    return sim, register([sim.slice], geom)


def _boxes(fig, gid):
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[1]
    texts = [t for t in ax.texts if t.get_gid() == gid]
    return ax, texts, [t.get_window_extent(renderer) for t in texts]


@pytest.mark.parametrize("pose", POSES)
def test_tube_labels_never_overlap_each_other_or_the_blobs(neuro_geometry, pose):
    import matplotlib.pyplot as plt

    sim, reg = _solved(neuro_geometry, pose)
    fig = overlay_figure([sim.slice], reg, tube_radius_mm=1.5)
    try:
        ax, texts, boxes = _boxes(fig, LABEL_GID)
        res = reg.slices[0]
        assert sorted(t.get_text() for t in texts) == sorted(res.assignment)
        for (ta, a), (tb, b) in itertools.combinations(zip(texts, boxes), 2):
            assert not a.overlaps(b), (ta.get_text(), tb.get_text())
        frame = ax.get_window_extent(fig.canvas.get_renderer())
        centres = ax.transData.transform(np.asarray(res.blobs_rc)[:, ::-1])  # (col, row) -> display
        radius = 1.5 / 0.5 * abs(ax.transData.transform([1, 0])[0] - ax.transData.transform([0, 0])[0])
        for t, b in zip(texts, boxes):
            assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1, t.get_text()
            for x, y in centres:  # no label covers any part of a blob (its own included)
                nearest = np.clip([x, y], [b.x0, b.y0], [b.x1, b.y1])
                assert np.hypot(*(nearest - (x, y))) > radius, t.get_text()
    finally:
        plt.close(fig)


def test_crowded_labels_are_pushed_apart_with_leader_lines():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from chic_register.outputs.overlay import place_labels

    fig, ax = plt.subplots(figsize=(3, 3))
    ax.set_xlim(0, 100)
    ax.set_ylim(100, 0)
    rng = np.random.default_rng(0)
    rc = 50 + rng.uniform(-6, 6, (9, 2))  # nine blobs within a few pixels: every naive label would collide
    try:
        texts = place_labels(ax, {f"T{k}": p for k, p in enumerate(rc)}, rc, radius_px=1.0)
        fig.canvas.draw()
        boxes = [t.get_window_extent(fig.canvas.get_renderer()) for t in texts]
        assert len(boxes) == 9
        assert not any(a.overlaps(b) for a, b in itertools.combinations(boxes, 2))
        assert len(ax.lines) >= 1  # at least one label was pushed aside, with a leader line to its blob
    finally:
        plt.close(fig)


def test_scale_bar_is_true_to_the_pixel_spacing(neuro_geometry):
    import matplotlib.pyplot as plt

    sim, reg = _solved(neuro_geometry, POSES[0], pixel_spacing_mm=(0.4, 0.4), shape=(320, 320))
    fig = overlay_figure([sim.slice], reg)
    try:
        ax = fig.axes[1]
        (bar,) = [line for line in ax.lines if line.get_gid() == SCALE_BAR_GID]
        (label,) = [t for t in ax.texts if t.get_gid() == SCALE_BAR_LABEL_GID]
        length_mm = float(label.get_text().removesuffix(" mm"))
        x = bar.get_xdata()
        assert abs(x[1] - x[0]) * 0.4 == pytest.approx(length_mm)
        view_mm = abs(np.diff(ax.get_xlim())[0]) * 0.4
        assert 0.1 * view_mm <= length_mm <= 0.25 * view_mm
    finally:
        plt.close(fig)
    assert scale_bar_mm(40.0) == 10.0 and scale_bar_mm(39.0) == 5.0 and scale_bar_mm(1.0) == 0.5


def test_view_is_cropped_on_the_fiducial_and_the_whole_image_shows_where(neuro_geometry):
    import matplotlib.pyplot as plt

    sim, reg = _solved(neuro_geometry, POSES[0])
    res = reg.slices[0]
    matched = np.asarray(res.blobs_rc)[list(res.assignment.values())]
    fig = overlay_figure([sim.slice], reg, tube_radius_mm=1.5)
    try:
        whole, ax = fig.axes[:2]
        (x0, x1), (y1, y0) = ax.get_xlim(), ax.get_ylim()
        # every matched blob inside the view, with room for a blob around it ...
        assert np.all(matched[:, 1] - 3 > x0) and np.all(matched[:, 1] + 3 < x1)
        assert np.all(matched[:, 0] - 3 > y0) and np.all(matched[:, 0] + 3 < y1)
        # ... and the view no larger than the fiducial's blobs plus a margin: a fraction of the 256 px image
        span = matched.max(axis=0) - matched.min(axis=0)
        assert x1 - x0 < 1.7 * span[1] and y1 - y0 < 1.7 * span[0] and x1 - x0 < 0.6 * 256
        # the left panel shows the whole image with a box around the zoomed region
        assert whole.get_xlim() == pytest.approx((-0.5, 255.5))
        (box,) = [p for p in whole.patches if p.get_gid() == ZOOM_BOX_GID]
        assert box.get_x() == pytest.approx(x0) and box.get_width() == pytest.approx(x1 - x0)
    finally:
        plt.close(fig)


def test_view_without_lock_spans_every_candidate():
    tubes = np.array([[120.0, 120.0], [140.0, 135.0]])
    extra = np.array([[5.0, 250.0]])
    lo, hi = view_bounds(np.vstack([tubes, extra]), (256, 256))
    assert lo[0] == 0.0 and hi[1] == 255.0  # the far blob is inside the view
    lo, hi = view_bounds(np.zeros((0, 2)), (256, 256))
    assert list(lo) == [0, 0] and list(hi) == [255, 255]


def test_no_lock_overlay_draws_the_candidates(neuro_geometry, tmp_path):
    sim = simulate_slice(neuro_geometry, 22.0, 20.0, 30.0, 15.0, rng=1)
    blobs = [detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)]
    path = draw_overlay(tmp_path / "o.png", [sim.slice], None, blobs, title="no lock: test")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_volume_overlay_draws_the_slices_its_joint_pose_left_out_with_their_reasons(zframe_geometry):
    """A real scan registered from some of its slices: each used slice has its fit's title, each left-out one its
    reason and the joint pose's crossings, matched by slice name (not by position in the list)."""
    vol = read_volume(REAL / "zframe-masked-b.nrrd")
    reg = register_volume(vol, zframe_geometry, prior=load_prior("RAS"))
    slices = [vol.native_slice(k) for k in range(vol.shape[0])]
    assert 0 < len(reg.slices) < len(slices) and reg.skipped
    predicted = [predicted_crossings_rc(zframe_geometry, reg.T_scanner_from_fiducial, sl) for sl in slices]
    fig = overlay_figure(slices, reg, predicted=predicted)
    titles = {sl.source: fig.axes[2 * j + 1].get_title() for j, sl in enumerate(slices)}
    for r in reg.slices:
        assert titles[r.source].startswith(f"depth {r.depth_mm:.2f} mm")
    for s in reg.skipped:
        assert titles[s.source].replace("\n", " ").startswith(f"left out: {s.reason[:40]}")


def test_slices_of_one_name_are_drawn_with_their_own_fits(neuro_geometry):
    """Two slices that share a name (two plain images both called "slice"): each drawn with its own fit."""
    import dataclasses

    slices, results = [], []
    for pose in POSES[:2]:
        sim, reg = _solved(neuro_geometry, pose)
        slices.append(dataclasses.replace(sim.slice, source="slice"))
        results.append(reg.slices[0])
    both = dataclasses.replace(reg, slices=tuple(results))
    fig = overlay_figure(slices, both)
    for j, r in enumerate(results):
        assert fig.axes[2 * j + 1].get_title().startswith(f"depth {r.depth_mm:.2f} mm")
    assert results[0].depth_mm != pytest.approx(results[1].depth_mm, abs=0.5)
