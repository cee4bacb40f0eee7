"""The solver's compiled kernels (numba, ``nopython`` mode): scalar loops over one pixel at a time.

``jit`` holds the shared ``njit`` (disk cache stamped with the package's kernel sources and
constants) and the sss kernel's erfcx; ``atomlm`` refines a pixel's atoms (Levenberg-Marquardt),
``pick`` / ``pickcorr`` pick the next atom from correlations at the pixel's own PSF width,
``onsets`` links sss onsets to their directs, and ``derivatives`` evaluates the kernels and their
parameter derivatives on blocks of pixels for the variable-projection refine and the Fisher
information (NumPy); ``projected`` is that refine's evaluation compiled (amplitudes, RSS, normal
equations, the Fisher information's Gram product) for point-sampled kernels of either
instrument (``response`` renders a measured response's table atoms), ``projlm`` that refine's
damped loop over them, one pixel at a time, and ``screen`` the
spatial neighbour starts' screen on the same kernels.  Nothing here imports the stages, the API or the evaluation code.
"""
