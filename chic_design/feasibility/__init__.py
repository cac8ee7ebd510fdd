"""The feasibility stage: the checks of ``chic-design check``, one module each, run by :mod:`.engine`.

No CAD kernel is needed: every check works on the geometry objects alone.
"""
