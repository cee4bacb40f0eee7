"""A stand-in for the one-time cost of a process's first decompose() call (compiling the kernels)."""


def first_call_costs_a_second(monkeypatch):
    """Make the first decompose() call of the process take a second longer, as a fresh compile does."""
    import functools
    import time

    import decomposition
    import decomposition.api
    import decomposition.warmup

    real, calls = decomposition.api.decompose, []

    @functools.wraps(real)
    def decompose(*args, **kwargs):
        if not calls:
            time.sleep(1.0)
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(decomposition, "decompose", decompose)
    monkeypatch.setattr(decomposition.api, "decompose", decompose)
    monkeypatch.setattr(decomposition.warmup, "decompose", decompose)  # the warm-up is a first call too
    return calls
