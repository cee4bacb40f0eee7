"""streaklab's napari plugin (the optional extra ``streaklab[napari]``).

The manifest ``napari.yaml`` contributes a reader for run, cube and result stores
(:mod:`._reader`), the pixel inspector and the maps widget (:mod:`._widgets`).  The data logic --
layer data tuples, scales, the live refresh, a pixel's profiles -- lives in :mod:`.layers`,
which imports neither napari nor Qt.  Nothing outside this package imports napari, Qt or npe2:
the core install runs without them.
"""
