"""``chic-design optimize``: the best CHIC fiducial for a tool, a printer and an imaging protocol.

Requirements (:mod:`.requirements`) -> design space (:mod:`.space`) -> scoring by
feasibility and the Cramér-Rao bound (:mod:`.score`, :mod:`.precision`) ->
NSGA-II search on a local pool or Dask (:mod:`.search`, :mod:`.engine`) with a
resumable store (:mod:`.store`) -> Pareto set, choice (:mod:`.choose`),
simulation confirmation (:mod:`.confirm`) and report (:mod:`.report`,
:mod:`.plots`), tied together by :func:`.pipeline.optimize`.
"""
