"""What residuals say of a measurement's errors beyond its noise: the model error (:class:`Scatter`).

A real image puts a tube's section 0.1-0.5 mm from where any rigid pose of the geometry file does (the gradients'
non-linearity, a rod bent or part-filled, the slab's partial volume at a frame's end); a simulation, within its
noise. The volume's joint fit (:mod:`chic_register.pipeline.every_slice`) and the verification of a pose fitted to
the pixels (:func:`chic_register.verify.pixels.section_model_error_mm`) read that error from the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scatter:
    """What residuals say of measured positions' errors (a joint fit's blob centres, the sections' offsets from a pose).

    ``noise_mm`` (M,): each position's 1-sigma error per coordinate
    from the image noise alone; ``model_error_mm``: the scatter beyond it that
    the residuals show (the same for every position, robust: from the median
    residual); ``sigma_mm`` (M,): both together.
    """

    noise_mm: np.ndarray
    model_error_mm: float

    @property
    def sigma_mm(self) -> np.ndarray:
        return np.sqrt(self.noise_mm ** 2 + self.model_error_mm ** 2)

    @classmethod
    def of(cls, r2_mm2: np.ndarray, noise_mm: np.ndarray) -> Scatter:
        """From squared residual lengths ``r2_mm2`` (M,) and centre noise ``noise_mm`` (M,): the model error whose
        total scatter puts the median of ``r2 / sigma^2`` at the chi-square (2 dof) median, 2 ln 2.

        Blob ``i``'s ratio exceeds the target exactly while ``m^2 < c_i = r2_i / target - noise_i^2``, so the median
        crosses it at the median of ``c`` (an odd count), or between the two middle ``c`` (an even count: the mean of
        two ratios, found by bisection inside that bracket)."""
        if r2_mm2.size == 0:
            return cls(noise_mm, 0.0)
        target = 2.0 * math.log(2.0)
        r2, n2 = np.asarray(r2_mm2, float), np.asarray(noise_mm, float) ** 2
        M = r2.size
        c = np.sort(r2 / target - n2)
        if M % 2:
            return cls(noise_mm, math.sqrt(max(float(c[M // 2]), 0.0)))

        def above(m: float) -> bool:  # the median ratio exceeds the target at model error m
            ratio = np.partition(r2 / np.maximum(n2 + m * m, 1e-300), (M // 2 - 1, M // 2))
            return 0.5 * (float(ratio[M // 2 - 1]) + float(ratio[M // 2])) > target

        lo, hi = math.sqrt(max(float(c[M // 2 - 1]), 0.0)), math.sqrt(max(float(c[M // 2]), 0.0))
        if not above(lo):
            return cls(noise_mm, lo)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if mid in (lo, hi):
                break
            lo, hi = (mid, hi) if above(mid) else (lo, mid)
        return cls(noise_mm, hi)
