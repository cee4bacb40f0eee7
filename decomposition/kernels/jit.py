"""Compiled scalar kernels shared by the solver's per-pixel loops (numba, ``nopython`` mode).

The hot parts of ConvSCD -- refining a pixel's few atoms and correlating its residual with
kernels at its own PSF width -- do a little work on many short windows.  As array
expressions over a block of pixels they spend most of their time allocating, placing and
masking window-shaped temporaries; compiled loops over one pixel at a time do the same
arithmetic without them.  Everything here is scalar: callers loop over pixels and samples.

All functions are compiled on first use and cached on disk next to this file (numba's
``cache=True``), so later processes -- dask workers included -- load them instead of compiling
again.  ``nogil=True`` lets the threaded scheduler run them in parallel.

A compiled kernel holds the values of the module-level constants it reads (``constants.py``,
other kernel modules), but numba keys its disk cache on the kernel's own source file alone: a
changed constant, or a changed kernel in another file, would be served from a stale cache --
silently wrong numbers after an upgrade that left ``__pycache__`` behind.  The kernels are
therefore cached under a stamp that also covers :func:`kernel_digest` of their package tree
(every module of the top-level package that uses ``njit``, in any of its folders, and its
``constants.py`` files): any change to those files compiles every kernel of the package afresh.
One folder alone would not do: the kernels of this folder read ``decomposition/constants.py``,
one level up.  Where numba's cache machinery cannot be extended so, the kernels are compiled
once per process instead of cached.

The forms are those of :mod:`core.model` (see its docstring): the sss kernel is
evaluated as g(x) erfcx(u) for u >= 0 and exp(-alpha (x - alpha sigma^2 / 2)) erfc(u) for
u < 0, so no exponential of a positive number is ever taken.
"""
from __future__ import annotations

import functools
import hashlib
import math
import os
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numba
import numpy as np
from numba.core import event as _numba_event

__all__ = ["njit", "erfcx", "sss_erfc_part", "sss_value", "compile_notice", "quiet_notice", "kernel_digest",
           "kernel_array"]

COMPILE_NOTICE = "compiling the solver's kernels once (about a minute on first use; later runs load them from the cache)"

SQRT_PI_2 = math.sqrt(math.pi / 2.0)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
_SQRT_2 = math.sqrt(2.0)
_ERFCX_SERIES_FROM = 10.0   # u at which the asymptotic series takes over from the table below
_ERFCX_STEP = 0.5           # width of the table's intervals in u
_ERFCX_DEGREE = 12          # degree of its polynomial on each


def _erfcx_table():
    """Power-series coefficients of erfcx on [j/2, (j+1)/2), j = 0 .. 19, in z = 4u - 2j - 1 (in [-1, 1]):
    (20, 13) float64, lowest degree first.

    Each piece is the Chebyshev interpolant of degree 12 at the 13 Chebyshev points of its
    interval (values from ``scipy.special.erfcx``; coefficients by the discrete cosine sums,
    then the integer coefficients of the Chebyshev polynomials T_k in powers of z), summed
    with ``math.fsum`` in plain floats: the same bits on every machine, where a least-squares
    fit through LAPACK would follow the CPU's kernels.  Largest relative error on [0, 10),
    read on a 200,001-point grid: 3.3e-15 (``tests/test_jit.py`` holds it below 1e-14).
    """
    from scipy import special

    deg = _ERFCX_DEGREE
    npts = deg + 1
    theta = [math.pi * (i + 0.5) / npts for i in range(npts)]
    z = [math.cos(t) for t in theta]
    # T_k(z) = sum_m cheb[k][m] z^m, from T_{k+1} = 2 z T_k - T_{k-1} (integers)
    cheb = [[1] + [0] * deg, [0, 1] + [0] * (deg - 1)]
    for k in range(2, npts):
        cheb.append([2 * (cheb[k - 1][m - 1] if m else 0) - cheb[k - 2][m] for m in range(npts)])
    n = int(round(_ERFCX_SERIES_FROM / _ERFCX_STEP))
    table = np.empty((n, npts))
    for j in range(n):
        f = [float(special.erfcx(_ERFCX_STEP * (j + 0.5 * (zi + 1.0)))) for zi in z]
        c = [(1.0 if k else 0.5) * 2.0 / npts * math.fsum(f[i] * math.cos(k * theta[i]) for i in range(npts))
             for k in range(npts)]
        for m in range(npts):
            table[j, m] = math.fsum(c[k] * cheb[k][m] for k in range(npts) if cheb[k][m])
    return table


_ERFCX_TABLE = _erfcx_table()


#: the files whose constants the kernels of a package read, beside the kernel modules themselves
CONSTANTS_FILE = "constants.py"
#: folders holding kernels made by :func:`njit` (their caches carry :func:`kernel_digest`)
_KERNEL_DIRS: set = set()


def _package_root(folder) -> Path:
    """The folder of the top-level package that holds ``folder`` (``folder`` itself when its
    parent is no package)."""
    root = Path(folder).resolve()
    while (root.parent / "__init__.py").is_file():
        root = root.parent
    return root


def kernel_array(a, dtype) -> np.ndarray:
    """``a`` as a C-contiguous, writable array of ``dtype`` for a compiled kernel: numba types a
    read-only array (a broadcast view, a frozen table) as a type of its own, so a kernel handed
    one where other calls hand a writable array compiles, and caches, a second time.  Copies only
    what is not already so."""
    return np.require(a, dtype, ["C", "W"])


@functools.lru_cache(maxsize=None)
def kernel_digest(folder) -> str:
    """SHA-256 (hex) of what the compiled kernels of ``folder`` are built from: the bytes of
    every ``constants.py`` and of every module that uses ``njit`` in the package tree that
    holds ``folder`` (:func:`_package_root`), with their paths in it.

    Computed once per process and folder (source files do not change under a running
    process; numba reads each kernel's own file once as well)."""
    h = hashlib.sha256()
    root = _package_root(folder)
    for path in sorted(root.rglob("*.py")):
        data = path.read_bytes()
        if path.name == CONSTANTS_FILE or b"njit" in data:
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + hashlib.sha256(data).digest())
    return h.hexdigest()


def _kernel_locators():
    """numba cache locators for the kernels of :data:`_KERNEL_DIRS` (numba's own user-provided,
    in-tree and user-wide locators, each with :func:`kernel_digest` added to its source stamp),
    or None where this numba's cache machinery is not laid out as expected."""
    try:
        from numba.core import caching
        impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
        bases = [getattr(caching, name, None) or getattr(caching, "_" + name)
                 for name in ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")]
        classes = impl._locator_classes
    except AttributeError:
        return None

    class _DigestStamp:
        def get_source_stamp(self):
            return (super().get_source_stamp(), kernel_digest(os.path.dirname(os.path.abspath(self._py_file))))

        @classmethod
        def from_function(cls, py_func, py_file):
            if os.path.dirname(os.path.abspath(py_file)) not in _KERNEL_DIRS:
                return None
            return super().from_function(py_func, py_file)

    ours = [type("Kernel" + base.__name__.lstrip("_"), (_DigestStamp, base), {}) for base in bases]
    if not any(getattr(c, "__name__", "").startswith("Kernel") for c in classes):
        classes[0:0] = ours
    return ours


_LOCATORS = _kernel_locators()


def njit(fn):
    """``numba.njit`` with the options every kernel of the solver uses.

    Compiled code is cached on disk (beside the source, else in the user's cache directory),
    under a stamp that covers the folder's :func:`kernel_digest` (see the module docstring).
    Where numba finds no writable place for it, or its cache cannot carry that stamp, the
    kernel is compiled without a cache, once per process, instead of failing the import or
    risking a stale kernel.
    """
    source = fn.__code__.co_filename
    if os.path.isfile(source):                # (code without a file is never cached)
        _KERNEL_DIRS.add(os.path.dirname(os.path.abspath(source)))
    if _LOCATORS is not None:
        try:
            return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
        except RuntimeError:          # "cannot cache function ...: no locator available"
            pass
    return numba.njit(cache=False, nogil=True, error_model="numpy")(fn)


@njit
def erfcx(u):
    """Scaled complementary error function exp(u^2) erfc(u) (float64).

    For 0 <= u < 10, a polynomial of degree 12 on each half-unit interval of u (the table of
    :func:`_erfcx_table`: relative error below 1e-14, about a third of the time of the two
    library calls exp(u^2) erfc(u)).  From u = 10 on, the asymptotic series 1/(u sqrt(pi))
    sum_n (-1)^n (2n-1)!! / (2u^2)^n (Abramowitz & Stegun 7.1.23) with 12 terms: its next term
    is below 1e-15 relative.  Negative u (and NaN) are evaluated as exp(u^2) erfc(u).
    """
    if u >= 0.0 and u < _ERFCX_SERIES_FROM:
        j = int(u * (1.0 / _ERFCX_STEP))
        z = 4.0 * u - (2.0 * j + 1.0)
        c = _ERFCX_TABLE[j]
        acc = c[_ERFCX_DEGREE]
        for m in range(_ERFCX_DEGREE - 1, -1, -1):
            acc = acc * z + c[m]
        return acc
    if u >= _ERFCX_SERIES_FROM:
        v = 1.0 / (2.0 * u * u)
        term = 1.0
        acc = 1.0
        for n in range(1, 13):
            term *= -(2.0 * n - 1.0) * v
            acc += term
        return acc * _INV_SQRT_PI / u
    return math.exp(u * u) * math.erfc(u)


@njit
def sss_erfc_part(u, g, f):
    """f(x) erfc(u) of the sss kernel (:func:`sss_value` without its factor sqrt(pi/2) sigma), from
    g = exp(-x^2 / (2 sigma^2)) and f = g exp(u^2) = exp(alpha^2 sigma^2 / 2 - alpha x) at the same x.

    g erfcx(u) for u >= 0; for u < 0, 2 f - g erfcx(-u) (erfc(u) = 2 - erfc(-u)): no
    cancellation, as g erfcx(-u) = f erfc(-u) <= f.  One :func:`erfcx` of a non-negative
    argument either way, so a caller that steps g and f from sample to sample evaluates no
    transcendental function per sample.  ``f`` is not read where u >= 0.
    """
    if u >= 0.0:
        return g * erfcx(u)
    return 2.0 * f - g * erfcx(-u)


@njit
def sss_value(x_ps, sigma_ps, alpha_per_ps):
    """sss kernel h(x) = (g * exp(-alpha t) u(t))(x) and the unit Gaussian g(x) at one time.

    ``x_ps`` is the time after the onset.  h = sqrt(pi/2) sigma g(x) erfcx(u) for
    u = (alpha sigma^2 - x) / (sigma sqrt 2) >= 0, and sqrt(pi/2) sigma
    exp(-alpha (x - alpha sigma^2 / 2)) erfc(u) otherwise (core.model).
    Returns (h, g).
    """
    g = math.exp(-0.5 * (x_ps / sigma_ps) ** 2)
    u = (alpha_per_ps * sigma_ps * sigma_ps - x_ps) / (sigma_ps * _SQRT_2)
    if u >= 0.0:
        h = g * erfcx(u)
    else:
        h = math.exp(-alpha_per_ps * (x_ps - 0.5 * alpha_per_ps * sigma_ps * sigma_ps)) * math.erfc(u)
    return SQRT_PI_2 * sigma_ps * h, g


class _CompileWatch(_numba_event.Listener):
    """Calls ``on_first`` when numba first starts compiling (a kernel not found in the disk cache)."""

    def __init__(self, on_first):
        self.on_first = on_first
        self.started = None

    def on_start(self, event):
        if self.started is None:
            self.started = time.monotonic()
            self.on_first()

    def on_end(self, event):
        pass


@contextmanager
def compile_notice(stream=None, *, label: str = "decompose"):
    """Say so, once, on ``stream`` (default stderr) if numba compiles anything within the block.

    Prints nothing when every kernel comes from numba's disk cache.  When something is compiled:
    one line as compiling starts, on a terminal a short count of seconds redrawn in place while it
    runs, and one line with the time it took at the end (over the count, on a terminal).  Yields the watch (``.started`` is None if
    nothing was compiled).
    """
    stream = sys.stderr if stream is None else stream
    tty = hasattr(stream, "isatty") and stream.isatty()
    done = threading.Event()

    def tick():
        while not done.wait(1.0):
            stream.write(f"\r{label}: compiling ... {time.monotonic() - watch.started:.0f} s")
            stream.flush()

    def on_first():
        stream.write(f"{label}: {COMPILE_NOTICE} ...\n")
        stream.flush()
        if tty:
            threading.Thread(target=tick, daemon=True, name="compile-notice").start()

    watch = _CompileWatch(on_first)
    try:
        with _numba_event.install_listener("numba:compile", watch):
            yield watch
    finally:
        done.set()
        if watch.started is not None:
            seconds = time.monotonic() - watch.started
            stream.write(("\r" if tty else "") + f"{label}: kernels compiled and cached in {seconds:.1f} s\n")
            stream.flush()


@contextmanager
def quiet_notice():
    """:func:`compile_notice` without the notice: yields a watch whose ``.started`` tells whether
    numba compiled anything within the block."""
    watch = _CompileWatch(lambda: None)
    with _numba_event.install_listener("numba:compile", watch):
        yield watch
