"""The print stage: the plate the printer gets (:mod:`.settings`, :mod:`.plate`), and the proof that every channel
survives slicing (:mod:`.slicer`, :mod:`.toolpaths`, :mod:`.check`)."""
