"""The parametric model the stages share: slot states and their atoms, component classes, refines.

``slots`` holds the per-pixel slot state (atoms by family, rendering, bounds, LM refine);
``components`` classifies and renders a fit's components; ``refine`` / ``varpro`` fit the
parameters by variable projection and ``fisher`` their Cramer-Rao errors; ``fidelity`` is the
distance of two component splits.
"""
