"""Register a volume's native slices: all of those that show the fiducial, or the ones asked for.

Real volumes are often masked or empty outside the frame, and the end
slices cut the tubes short: :func:`register_volume` without indices tries
every slice, registers jointly those where the fiducial locks and reports the
others (:attr:`~chic_register.solve.Registration.skipped`, with the reason,
and the residual of a slice that disagrees with the rest).
:func:`parse_slice_indices` reads ``--slices`` values (``5``, ``5-11``).
"""

from __future__ import annotations

from .errors import ChicRegisterError
from .geometry import FiducialGeometry
from .solve import Registration, register
from .volume import Volume


def parse_slice_indices(tokens, n_slices: int, source: str = "--slices") -> list[int]:
    """Slice indices from tokens such as ``"5"``, ``"5-11"`` (inclusive), ``"-1"`` (the last); in order, no repeats.

    Raises :class:`ChicRegisterError` naming the bad token and what is allowed.
    """
    out: list[int] = []
    for tok in tokens:
        text = str(tok).strip()
        try:
            if "-" in text[1:]:  # a range; a leading '-' alone is a negative index
                cut = text.index("-", 1)
                a, b = int(text[:cut]), int(text[cut + 1:])
                if a > b:
                    raise ChicRegisterError(f"{source} {text}: a range runs from low to high (e.g. 5-11)")
                values = range(a, b + 1)
            else:
                values = [int(text)]
        except ValueError:
            raise ChicRegisterError(f"{source} {text}: not a slice index or range; use e.g. 5 or 5-11") from None
        for k in values:
            if not -n_slices <= k < n_slices:
                raise ChicRegisterError(f"{source} {text}: slice index {k} is outside 0..{n_slices - 1}")
            k %= n_slices
            if k not in out:
                out.append(k)
    return out


def register_volume(volume: Volume, geom: FiducialGeometry, indices=None, **options) -> Registration:
    """One pose from a volume's native k-slices.

    ``indices`` None: every slice is tried and those that do not lock, or
    disagree with the others, are skipped (listed with their reasons); else
    exactly those slices, each of which must lock. ``options`` go to
    :func:`~chic_register.solve.register`.
    """
    nk = volume.shape[0]
    ks = range(nk) if indices is None else indices
    slices = [volume.native_slice(k) for k in ks]
    return register(slices, geom, skip_failed=indices is None, **options)
