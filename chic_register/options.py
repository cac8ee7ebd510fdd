"""The solver's options: trust thresholds and search settings of :func:`chic_register.pipeline.register.register`.

Every stage reads its settings from one :class:`SolveOptions`; the module sits below every stage so that each can.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Default trust limits (``SolveOptions.trust_tre_mm`` / ``trust_rot_deg``): the predicted error (TRE at the frame
#: centre, rotation) at :data:`~chic_register.fit.checks.PRECISION_SIGMAS` standard deviations. Why these limits: a
#: single slice near normal to the axis knows its tilt to 0.2-0.25 deg (1 sigma, the Cramer-Rao bound at SNR 20), so
#: a 0.5 deg limit refuses the paper's own protocol; a wrong pose that survived the image checks fits with a residual
#: scatter well above its noise, and in the false-lock hunt (benchmarks/hunt.py, 5000 cases) every such pose had a
#: 3-sigma rotation above 0.8 deg, while the correct poses that 0.75 deg lets through were all within 0.5 mm, 0.5 deg.
TRE_TOL_MM = 1.0
ROT_TOL_DEG = 0.75
#: Default largest relative scale of an image along any axis that the solver fits with the pose rather than
#: refuses (``SolveOptions.max_scale_error``): clinical scanners' gradient calibration holds the scale to 1-2 %
#: (a larger one is a wrong pixel spacing, and the message names the spacing that would register it), a print
#: shrinks or grows by 0.1-0.5 %.
MAX_SCALE_ERROR = 0.02
#: The same across a volume's slices (``SolveOptions.max_slice_scale_error``): scanners correct the gradients'
#: non-linearity in the image plane (2-D correction is the default of most 2-D and many 3-D protocols) but not across
#: it, and 100-150 mm from the isocentre, where a frame on the perineum or the head sits, the slice direction's local
#: scale is off by several per cent (a real prostate-template scan: -3 %); a wrong slice spacing is off by more
#: (a missing gap, overlapping slices read as contiguous: 10-50 %).
MAX_SLICE_SCALE_ERROR = 0.05


@dataclass(frozen=True)
class SolveOptions:
    """Trust thresholds and search settings of :func:`register`.

    ``max_rms_px``: largest accepted RMS residual, in pixels of each slice;
    ``max_residual_px``: largest accepted single-tube residual; ``min_tubes``
    and ``min_depth_tubes``: fewest matched tubes in all, and of tubes not
    parallel to the axis (helices), needed for a lock; ``ambiguity_ratio``:
    a distinct second pose matching as many tubes with an RMS within this
    factor of the best makes the fit ambiguous (a pose that leaves a tube
    unexplained loses: near-symmetric layouts always have one that fits all
    but one tube). ``centroid_model``: after the lock, refit predicting
    each tube's section centroid as the detector measures it, not its
    centreline crossing (:func:`centroid_offsets`; removes the bias of
    curved, clipped and touching sections at a few ms per iteration:
    ``centroid_iterations`` renders of every matched tube's footprint with
    ``centroid_supersample``² samples per pixel and
    ``centroid_thickness_samples`` sub-planes). Then, ``template_iterations``
    times, each clean tube's position is measured by fitting its rendered
    section to the pixels (:func:`template_shifts`; about 1.5 times more
    precise than a centroid in white noise) and the pose refitted on those;
    a template landing more than ``template_max_disagreement_px`` from the
    centroid model's position gives :class:`NoLock`. 0 turns it off.
    ``section_fit`` (the default mode, unless ``centroid_model``): after the
    lock, each matched tube's section is located by fitting an analytic
    model of it to its pixels (:mod:`chic_register.fit.section`, with
    ``section_thickness_samples`` planes across the slice) and the pose is
    refitted on those positions, weighted by their information; up to
    ``section_iterations`` passes (see :func:`_section_refine`); tubes whose
    fit lands more than ``section_max_shift_px`` from the pose's prediction
    are left out. Off: the pose fitted to blob centroids (faster, biased).
    ``section_rician``: where the image's background is Rayleigh (a magnitude
    image), the section fit models the Rician mean of the pixels
    (:mod:`chic_register.imaging.rician`): a linear model reads the lifted faint
    edges as a sub-pixel shift, a bias growing with the noise.
    ``section_blur``: each slice's point spread (scanners' k-space filters,
    the blob widening of real images) is measured with the sections and
    drawn into their model; without it a sharp model weights blurred edges
    wrongly and claims their sharpness as precision.
    ``verify``: before ``ok``, prove the pose against the image
    (:mod:`chic_register.verify.pixels`: envelope, every predicted section
    present with its shape, nothing unexplained on the tubes' circle, pixel
    spacing, no rival that explains the pixels nearly as well, and a
    predicted error (3 sigma) within ``trust_tre_mm`` at the frame centre and
    ``trust_rot_deg``; when only that last test fails, the section fit is
    tried again without a section the damage pulled off alone, held to 4.5
    sigma (:func:`_without_outlier_sections`), and then, with
    ``refine_when_imprecise``, the accuracy mode's refinement, before
    refusing); off only for studies of the raw fit.
    ``blurred_fit``: when the blobs are clearly wider than the channels,
    the pose is fitted to the pixels through a blurred model of all the
    sections at once (:mod:`chic_register.fit.blurred`) instead of the
    section fit, and verified with that fit's precision.
    ``uncertainty``: compute the pose's covariance and predicted TRE
    (:mod:`~chic_register.precision.uncertainty`; a few ms per slice; always when
    ``max_tre_mm`` is finite); ``max_tre_mm``: a pose whose predicted TRE at
    the registration's target exceeds it gives :class:`NoLock` (``imprecise``).
    ``prior``: an approximate ``T_scanner_from_fiducial`` (4x4, only its
    rotation is used): poses turned more than ``prior_max_deg`` from it are
    never considered. It is what resolves a geometry that maps onto itself
    under a rotation (the classic Z-frame does, under a half turn): without
    it, such a fit is refused as ambiguous.
    ``fit_scale``: the verified pose is fitted again with the image's scale
    per axis (:mod:`chic_register.fit.scale`); where the data show a scale
    (its F test below :data:`~chic_register.fit.checks.STRETCH_P`) the pose
    so fitted is the answer and its covariance holds the scale's
    uncertainty; ``max_scale_error``: a scale in the image plane beyond it
    is refused as a wrong pixel spacing, ``max_slice_scale_error`` one
    across a volume's slices as a wrong slice spacing (the registration
    reports the scale either way). ``scale_sd``: the in-plane scale's
    standard deviation known beforehand (a print's size against its
    geometry file, a scanner's gradient calibration: 0.1-0.7 % uncalibrated,
    a calibrated file's own SD after ``chic-register calibrate``), for a
    registration that cannot measure it (one slice): its effect on the pose
    joins the covariance and the trust test. None (the default): a
    calibrated geometry file's recorded SD, else 0 (the geometry file and
    the pixel spacing taken as exact; the registration still reports how
    much an unmeasured scale would move the pose).
    """

    max_rms_px: float = 0.5
    max_residual_px: float = 1.5
    min_tubes: int = 6
    min_depth_tubes: int = 2
    ambiguity_ratio: float = 3.0
    max_hypotheses: int = 4
    max_tilt_deg: float = 75.0
    centroid_model: bool = False
    centroid_iterations: int = 4
    centroid_supersample: int = 5
    centroid_thickness_samples: int = 5
    centroid_min_purity: float = 0.93
    template_iterations: int = 1
    template_max_disagreement_px: float = 0.5
    section_fit: bool = True
    section_iterations: int = 5
    section_close_px: float = 0.2
    section_done_px: float = 0.05
    section_thickness_samples: int = 5
    section_max_shift_px: float = 1.0
    section_rician: bool = True
    section_blur: bool = True
    verify: bool = True
    trust_tre_mm: float = TRE_TOL_MM  # (why these limits: TRE_TOL_MM above)
    trust_rot_deg: float = ROT_TOL_DEG
    refine_when_imprecise: bool = False
    blurred_fit: bool = True
    max_tre_mm: float = math.inf
    uncertainty: bool = True
    prior: np.ndarray | None = None
    prior_max_deg: float = 60.0
    fit_scale: bool = True
    max_scale_error: float = MAX_SCALE_ERROR
    max_slice_scale_error: float = MAX_SLICE_SCALE_ERROR
    scale_sd: float | None = None
