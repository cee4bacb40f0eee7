"""The chunked store pipeline, a layer above the solver: cube store in, result store out.

``pipeline`` maps :func:`decomposition.decompose` over the pixel chunks of a cube store
(``chunked``, with dask; ``cluster`` for a distributed scheduler) and writes a result store
(``resultstore``).  The only part of ``decomposition`` that reads cube stores (``reconstruction``).
"""
