"""The measured-response path: decomposition with an instrument response (``decompose(irf=...)``).

``resolve`` checks and resamples the ``irf=`` argument, ``dictionary`` renders the response's
atoms, ``detect`` / ``grow`` / ``refine`` fit slot atoms under the Poisson or Gaussian
deviance, ``label`` / ``fisher`` label them and give their errors, ``atoms`` renders a slot's
atoms, and ``path`` runs the whole path for :func:`decomposition.decompose`.
"""
