"""CHIC design: a parametric, printable CHIC fiducial from a YAML spec."""

from chic_register.version import __version__

__all__ = ["__version__"]
