"""The version of the chic package (both programs and every file they write carry it)."""

__version__ = "0.1.0"
