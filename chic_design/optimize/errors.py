"""Domain exceptions of ``chic-design optimize`` (one-line messages; the CLI exits with ``exit_code``)."""

from __future__ import annotations

from chic_design.errors import ChicDesignError


class RequirementsError(ChicDesignError):
    """A requirements file that is missing, not YAML, or has an unknown, wrong or contradictory value."""


class NoFeasibleDesign(ChicDesignError):
    """The search found no candidate that meets every requirement (nothing is written as a design)."""

    exit_code = 4
