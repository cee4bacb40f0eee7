"""The stage modules :func:`decomposition.decompose` calls, on blocks of pixels.

The order they run in is declared once, in :data:`decomposition.api.STAGES` (each stage a name,
the function in ``api.py`` that calls its module here, and a one-line purpose); docs/decomposition.md
lists the same names in the same order.  Besides the modules those stages call (``prepare``,
``detect``, ``search``, ``grow``, ``prune``, ``countpolish``, ``label``, ``refit``, ``quality``,
``rescue``), ``candidates`` holds the helpers the stages after the detection share (signal and
correlated noise, polishing a candidate set), ``objective`` the penalised objective they compare
fits by, and ``background`` the per-pixel offset's estimate and test.
"""
