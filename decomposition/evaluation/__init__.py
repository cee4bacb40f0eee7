"""Evaluation code for benchmarks and tests: synthetic scenes, reference fits and accuracy.

``synthetic`` (with ``scenes``, ``synthetic_effects``, ``synthetic_noise``) draws profiles with
ground truth; ``oracle``, ``best_found`` and ``poisson_reference`` give reference fits;
``metrics`` scores decompositions against the truth.  The solver never imports this package.
"""
