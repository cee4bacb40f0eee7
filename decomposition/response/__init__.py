"""What a measured instrument response (``decompose(irf=...)``) does differently in the stages.

The stage list (:data:`decomposition.api.STAGES`), the labels' rule, the flags' rules and the
standard errors are the Gaussian path's, given the response's atoms
(:mod:`decomposition.model.atoms`), and so is the detection's code
(:func:`decomposition.stages.detect.detect_components`).  Here: ``resolve`` checks and resamples
the ``irf=`` argument, ``refine`` / ``grow`` fit slot atoms under the Poisson or Gaussian
deviance, ``label`` names them, and ``path`` holds the response's implementations of the
``detect``, ``label``, ``refit``, ``forward_steps``, ``offset_test`` and ``final_atoms`` stages.
"""
