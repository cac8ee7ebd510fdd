"""Domain exceptions of the design pipeline, in one place.

The CLI prints ``str(exc)`` as one line and exits with ``exit_code``.
"""

from __future__ import annotations


class ChicDesignError(Exception):
    """Base class: a failure the user can act on."""

    exit_code = 2


class SpecError(ChicDesignError):
    """A spec that is missing, not YAML, or has an unknown, wrong or contradictory value."""


class InfeasibleDesign(ChicDesignError):
    """The feasibility checks found violations (``build`` refuses unless ``--force``)."""

    exit_code = 4

    def __init__(self, spec_path, violations, forceable: bool = True):
        self.violations = list(violations)
        # one line per violation: a long list on a single line is unreadable
        lines = "".join(f"\n  - {v.code} ({v.where}): {v.message}" for v in self.violations)
        n = len(self.violations)
        hint = "fix the spec or build anyway with --force" if forceable else "fix the spec; --force cannot build it"
        super().__init__(f"{spec_path}: design is infeasible ({n} violation{'s' if n != 1 else ''}; {hint}):{lines}")


class BuildCheckError(ChicDesignError):
    """The build's own output checks failed; nothing was written over an earlier export."""

    exit_code = 5


class PrintFileError(ChicDesignError):
    """A plate, G-code or export folder that cannot be read for the print check."""


class SlicerError(ChicDesignError):
    """The slicer is missing or could not slice the plate (its own last message is quoted)."""

    exit_code = 3


class ChannelsNotPrintable(ChicDesignError):
    """The print check found a channel closed, narrowed or overhanging in the sliced toolpaths."""

    exit_code = 6
