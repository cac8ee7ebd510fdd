"""Domain exceptions of the registration solver, in one place.

Every exception here is a user-facing failure: the CLI prints ``str(exc)`` as
one line and exits with ``exit_code``; no traceback is shown for them.
"""

from __future__ import annotations


class ChicRegisterError(Exception):
    """Base class: a failure the user can act on."""

    exit_code = 2


class InputFileError(ChicRegisterError):
    """An input file refused before its content is used: not a regular file, too large, unsafe YAML."""

    def __init__(self, path, message: str):
        self.path = str(path)
        self.detail = message
        super().__init__(f"{self.path}: {message}")


class GeometryFileError(ChicRegisterError):
    """A geometry file that is missing, malformed, of a wrong format/version or fails its hash."""

    def __init__(self, path, message: str):
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


class ImageReadError(ChicRegisterError):
    """An image file that is missing, unreadable, truncated or not an image."""

    def __init__(self, path, message: str):
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


class OutputError(ChicRegisterError):
    """An output that cannot be written or sent (a missing folder, a closed OpenIGTLink peer)."""


class NoLock(ChicRegisterError):
    """No trustworthy pose: the solver refuses rather than guess (exit 3)."""

    exit_code = 3

    def __init__(self, reason: str, detail: dict | None = None):
        self.reason = reason
        self.detail = detail or {}
        super().__init__(reason)


class AmbiguousFit(NoLock):
    """Two distinct poses explain the blobs nearly equally well (in one slice of a series, the others may decide)."""


class SliceRefused(NoLock):
    """Slices of a series fail the pose's verification (``refused``: their places in the series and reasons): a
    volume's registration leaves them out and verifies the rest."""

    def __init__(self, reason: str, detail: dict | None = None, refused: tuple = ()):
        super().__init__(reason, detail)
        self.refused = tuple(refused)


class ImprecisePose(NoLock):
    """A pose that verifies but whose predicted error exceeds the trust limits (the solver may refine it first)."""
