"""The parametric model the stages share: slot states and their atoms, component classes, refines.

``slots`` holds the per-pixel slot state (atoms by family, rendering, bounds, LM refine);
``atoms`` renders a measured response's atoms for slot arrays; ``components`` classifies and
renders a fit's components and holds the rules on them (threshold, merge, window measures) for
either instrument; ``refine`` / ``varpro`` fit the parameters by variable projection and
``fisher`` their Cramer-Rao errors (either instrument); ``fidelity`` is the distance of two
component splits.
"""
