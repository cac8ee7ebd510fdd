"""CHIC registration solver: find a line fiducial's 6-DOF pose (CHIC, Z-frame) in MRI and CT slices.

The solver reads only a geometry file (``geometry.yaml``, see
:mod:`chic_register.model.geometry`); it never reads a design spec.

The public API is below; each name loads its module on first use, so that
``import chic_register`` costs nothing (a one-shot command stays fast)::

    import chic_register as cr

    geom = cr.load_geometry("exports/neuro/geometry.yaml")
    reg = cr.register(cr.read_slices("slice.dcm"), geom)
    reg.T_scanner_from_fiducial

The packages are the pipeline's stages, lowest first: ``util``, ``model``,
``io``, ``imaging``, ``detect``, ``guess``, ``fit``, ``verify``,
``precision``, ``pipeline``, ``outputs``, ``live``, ``studies``, ``cli``.
"""

from chic_register.version import __version__

#: Public name -> the module that defines it.
API_HOMES = {
    "register": "chic_register.pipeline.register",
    "register_volume": "chic_register.pipeline.volume",
    "Registration": "chic_register.pipeline.results",
    "SliceResult": "chic_register.pipeline.results",
    "SkippedSlice": "chic_register.pipeline.results",
    "SolveOptions": "chic_register.options",
    "load_geometry": "chic_register.model.geometry",
    "write_geometry": "chic_register.model.geometry",
    "FiducialGeometry": "chic_register.model.geometry",
    "Slice": "chic_register.model.slices",
    "read_slices": "chic_register.io.images",
    "read_volume": "chic_register.io.volumes",
    "write_volume": "chic_register.io.volumes",
    "Volume": "chic_register.io.volumes",
    "write_dicom": "chic_register.io.dicom",
    "simulate_slice": "chic_register.imaging.simulate",
    "simulate_volume": "chic_register.imaging.simulate",
    "PoseUncertainty": "chic_register.precision.uncertainty",
    "ChicRegisterError": "chic_register.errors",
    "NoLock": "chic_register.errors",
    "ImageReadError": "chic_register.errors",
    "GeometryFileError": "chic_register.errors",
}

__all__ = ["__version__", *API_HOMES]


def __getattr__(name: str):
    """The public name ``name``, imported from its module on first use (PEP 562)."""
    module = API_HOMES.get(name)
    if module is None:
        raise AttributeError(f"module 'chic_register' has no attribute {name!r}")
    import importlib  # deferred: only a public name asked for needs it

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(__all__)
