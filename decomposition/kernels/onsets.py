"""The onset-tie rule: when an sss onset moves with the direct reflection.

Light enters a surface where it is directly reflected, so with ``sss_after_direct`` an sss
onset close before the direct (the earliest Gaussian) is tied to it: refined as direct delay
+ gap with gap >= 0, and never moved before it.  "Close" is less than ``near_sigma`` PSF
widths (:data:`~decomposition.constants.NEAR_SIGMA` unless a caller says otherwise: the polish
retries every onset, ``near_sigma = inf``).  :func:`onset_link` is the rule for one pixel,
compiled, called by the LM loop of :mod:`decomposition.kernels.atomlm`; :func:`onset_links` applies
it to a block's slot arrays for the numpy steps (:func:`decomposition.model.slots.linked_onsets`).
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import FAM_GAUSS, FAM_SSS, NEAR_SIGMA
from .jit import njit

__all__ = ["onset_link", "onset_links"]


@njit
def onset_link(K, fam, delay, lsig, near_sigma):
    """The onset-tie rule, for one pixel: (linked, direct slot, sss slot).

    The direct is the earliest Gaussian (the first of equal delays), the sss slot the first
    sss atom.  Linked: the pixel has both, and the direct lies less than ``near_sigma`` PSF
    widths (the sss atom's) after the sss onset.  Slots default to 0 where absent.
    """
    dsl = 0
    first = np.inf
    ssl = -1
    for k in range(K):
        if fam[k] == FAM_GAUSS and delay[k] < first:
            first = delay[k]
            dsl = k
        if fam[k] == FAM_SSS and ssl < 0:
            ssl = k
    linked = ssl >= 0 and first < np.inf and first - delay[ssl] < near_sigma * math.exp(lsig[ssl])
    if ssl < 0:
        ssl = 0
    return linked, dsl, ssl


@njit
def _onset_link_rows(fam, delay, lsig, near_sigma, linked, dsl, ssl):
    K = fam.shape[1]
    for i in range(fam.shape[0]):
        linked[i], dsl[i], ssl[i] = onset_link(K, fam[i], delay[i], lsig[i], near_sigma)


def onset_links(fam, delay_ps, lsig, near_sigma=NEAR_SIGMA):
    """:func:`onset_link` for every row of (P, K) slot arrays -> (linked (P,) bool, direct slot (P,),
    sss slot (P,))."""
    fam = np.ascontiguousarray(fam, dtype=np.int8)
    P = fam.shape[0]
    linked = np.zeros(P, np.bool_)
    dsl = np.zeros(P, np.int64)
    ssl = np.zeros(P, np.int64)
    if P:
        _onset_link_rows(fam, np.ascontiguousarray(delay_ps, dtype=np.float64),
                         np.ascontiguousarray(lsig, dtype=np.float64), float(near_sigma), linked, dsl, ssl)
    return linked, dsl, ssl
