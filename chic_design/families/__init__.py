"""The fiducial families, registered in one place: :data:`FAMILIES`.

Each family (:class:`~chic_design.families.base.Family`) lives in its own
folder; the generic code finds a spec's family with :func:`family_of` and a
named one with :func:`family_named`. Adding a family: its folder and one
line in :data:`FAMILIES`.
"""

from __future__ import annotations

from chic_design.errors import SpecError
from chic_design.families.base import Family
from chic_design.families.chic import ChicFamily
from chic_design.families.nlocalizer import NLocalizerFamily
from chic_design.families.zframe import ZFrameFamily

#: Every family by its ``family`` value, in the order messages list them.
FAMILIES: dict[str, Family] = {"chic": ChicFamily(), "zframe": ZFrameFamily(), "nlocalizer": NLocalizerFamily()}
#: The family of a spec without a ``family`` key.
DEFAULT_FAMILY = "chic"


def family_named(name, where: str = "family") -> Family:
    """The family called ``name``; a :class:`SpecError` ``<where>: unknown family ...; allowed: ...`` otherwise."""
    if isinstance(name, str) and name in FAMILIES:
        return FAMILIES[name]
    raise SpecError(f"{where}: unknown family {name!r}; allowed: {', '.join(FAMILIES)}")


def family_of(spec) -> Family:
    """The family of a validated spec (its ``family`` key)."""
    return family_named(spec.family)


def geometry_of(spec, source: dict | None = None):
    """The geometry model of a validated spec of any family: ``family_of(spec).geometry(spec, source)``."""
    return family_of(spec).geometry(spec, source)
