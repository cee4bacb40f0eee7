"""The two decomposition methods: ConvSCD (the solver) and GradBM (the baseline).

``convscd`` is the per-pixel convolutional sparse coding over the kernel ``dictionary``
(``score`` ranks candidate atoms, ``polish`` refits amplitudes and snaps atoms to the grid);
``gradbm`` is the paper's gradient-based baseline, run by ``decompose(method="gradbm")``.
"""
