"""Two fiducials in one slice: a CHIC inside an N-localizer frame, both registered from the same image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from chic_register.model.pose import invert
from chic_register.options import SolveOptions
from chic_register.pipeline.frames import mask_sections, register_frames, relative_pose, section_mask
from tests.helpers import LEKSELL_T, both_in_one_slice, three_plate_frame


def _pose_error(T, T_true, point):
    p = np.append(point, 1.0)
    return float(np.linalg.norm((T @ p - T_true @ p)[:3]))


@pytest.mark.parametrize("modality", ["MR", "CT"])
def test_a_chic_inside_a_frame_registers_with_it_and_maps_into_frame_coordinates(neuro_geometry, modality):
    frame = three_plate_frame()
    sl, T_frame, T_chic = both_in_one_slice(frame, neuro_geometry, 20.0, modality)
    prior = SolveOptions(prior=np.eye(4))  # the frame is symmetric under a half turn: its mounting is known
    results = register_frames([sl], [neuro_geometry, frame], options_for=lambda i: prior if i == 1 else None)
    assert [r.ok for r in results] == [True, True], [r.reason for r in results]
    chic_reg, frame_reg = (r.registration for r in results)
    assert _pose_error(frame_reg.T_scanner_from_fiducial, T_frame, (0, 0, 60)) < 0.3
    assert _pose_error(chic_reg.T_scanner_from_fiducial, T_chic, (0, 0, 25)) < 0.3
    # neither took the other's blobs: no detected centre is assigned to both
    a = np.array([chic_reg.slices[0].blobs_rc[i] for i in chic_reg.slices[0].assignment.values()])
    b = np.array([frame_reg.slices[0].blobs_rc[i] for i in frame_reg.slices[0].assignment.values()])
    assert len(a) >= 7 and len(b) == 9
    assert np.min(np.linalg.norm(a[:, None] - b[None], axis=-1)) > 4.0
    rel = relative_pose(chic_reg, neuro_geometry, frame_reg, frame)
    true = LEKSELL_T @ invert(T_frame) @ T_chic
    expected = true[:3, :3] @ rel.target_a_mm + true[:3, 3]
    assert rel.frame == "leksell"
    assert np.linalg.norm(rel.target_b_mm - expected) < 0.3
    # the reported uncertainty is an honest size: within a few sigma of the actual error, and not vanishing
    assert 0 < rel.tre_mm < 0.3
    assert np.linalg.norm(rel.target_b_mm - expected) < 5 * rel.tre_mm + 0.02


def test_relative_pose_adds_both_covariances_by_hand():
    """Translation-only covariances: the point's covariance in the frame is the sum, turned into frame axes."""
    from chic_register.precision.uncertainty import PoseUncertainty

    frame = three_plate_frame()

    def reg(T, var_mm2):
        cov = np.zeros((6, 6))
        cov[3:, 3:] = np.diag(var_mm2)
        unc = PoseUncertainty(cov, (), 1.0, 1, 1.0, (0.0, 0.0, 0.0), 0.0)
        from chic_register.pipeline.results import Registration
        return Registration("ok", T, (), {}, uncertainty=unc)

    T_a = np.eye(4)
    T_a[:3, 3] = [10, 20, 30]
    T_b = np.eye(4)
    a, b = reg(T_a, [0.01, 0.04, 0.09]), reg(T_b, [0.01, 0.0, 0.0])
    tool = dataclasses.replace(frame, name="tool", frame_coordinates=None)
    rel = relative_pose(a, tool, b, frame, target_a_mm=(0.0, 0.0, 0.0))
    assert np.allclose(rel.target_b_mm, LEKSELL_T[:3, :3] @ [10, 20, 30] + LEKSELL_T[:3, 3])
    assert np.allclose(np.diag(rel.covariance_mm2), [0.02, 0.04, 0.09])


def test_masking_a_fiducials_sections_removes_its_blobs_and_marks_them_lost(neuro_geometry):
    frame = three_plate_frame()
    sl, T_frame, _ = both_in_one_slice(frame, neuro_geometry, 20.0, "MR")
    mask = section_mask(sl, frame, T_frame)
    masked = mask_sections(sl, mask)
    assert masked.lost is not None and masked.lost.sum() == mask.sum() > 0
    # the frame's nine sections were bright; now nothing in the mask stands out from its surroundings
    assert sl.pixels[mask].max() > 0.8 and masked.pixels[mask].max() < 0.2


@pytest.mark.parametrize("modality", ["MR", "CT"])
def test_a_chic_inside_the_leksell_box_registers_from_one_tilted_slice(neuro_geometry, modality):
    """The Leksell G CT box of designs/: two lateral plates, so the slice is tilted (15 deg about F's x) to fix
    the turn about x; the box needs its prior, the CHIC does not."""
    from chic_design.families import family_named
    from chic_design.spec import load_spec
    from tests.helpers import ROOT

    box = family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / "leksell-g-ct.yaml"))
    sl, T_frame, T_chic = both_in_one_slice(box, neuro_geometry, 15.0, modality)
    prior = SolveOptions(prior=np.eye(4))
    results = register_frames([sl], [neuro_geometry, box], options_for=lambda i: prior if i == 1 else None)
    assert [r.ok for r in results] == [True, True], [r.reason for r in results]
    chic_reg, frame_reg = (r.registration for r in results)
    rel = relative_pose(chic_reg, neuro_geometry, frame_reg, box)
    true = LEKSELL_T @ invert(T_frame) @ T_chic
    assert np.linalg.norm(rel.target_b_mm - (true[:3, :3] @ rel.target_a_mm + true[:3, 3])) < 0.3
    assert _pose_error(frame_reg.T_scanner_from_fiducial, T_frame, (0, 0, 60)) < 0.3
