"""CHIC registration solver: find a CHIC fiducial's 6-DOF pose in MRI slices.

The solver reads only a geometry file (``geometry.yaml``, see
:mod:`chic_register.model.geometry`); it never reads a design spec.
"""

from chic_register.version import __version__  # noqa: F401
