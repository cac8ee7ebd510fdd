"""CHIC registration solver: find a CHIC fiducial's 6-DOF pose in MRI slices.

The solver reads only a geometry file (``geometry.yaml``, see
:mod:`chic_register.geometry`); it never reads a design spec.
"""

__version__ = "0.1.0"
