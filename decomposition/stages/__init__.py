"""The stages :func:`decomposition.decompose` runs, in order, on blocks of pixels.

``prepare`` (checks, noise, spikes, background), ``detect`` (the method's first answer),
``candidates`` (shared helpers of the stages that try alternatives), ``search`` (structured
starts), ``grow`` / ``prune`` (add or drop an atom where the objective says so; ``objective``
is the measure they compare fits by), ``countpolish`` (count data), ``refit`` (final
refine, errors, background), ``label`` (physical labels and flags), ``quality`` (fit quality
flags), ``rescue`` (a second pass for misfit pixels) and ``background``.
"""
