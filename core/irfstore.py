"""Storing an instrument response: a Zarr group (standalone or inside a cube store) or a ``.npz`` file.

Layout of a response group (``streaklab_kind = "instrument_response"``)::

    response  (irf_t,)  float64   the samples, 1/ps, unit area
    irf_t     (irf_t,)  float64   sample times relative to the response's reference instant, ps

Group attributes: ``streaklab_kind``, ``format_version``, ``time_step_ps``, ``t0_ps``,
``units`` (``"1/ps"``), ``normalization`` (``"unit area"``), ``reference`` (what t = 0 is),
``peak_time_ps``, ``fwhm_ps``, ``model`` (the closed form of a model response, or null),
``provenance`` (where the response came from: source store, pixels used, date, software
version), ``software_version`` and ``created_utc`` of the write.  Both arrays name their
dimension, so ``xarray.open_zarr(path, consolidated=False)`` (``group="irf"`` inside a cube)
opens it as a dataset with coordinate ``irf_t``.

A ``.npz`` file holds the same: arrays ``response`` and ``irf_t``, and ``attributes``, the
group attributes as a JSON string.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
from pathlib import Path

import numpy as np
import zarr

from .calibfile import open_calibration, save_calibration
from .integrity import create_array, read_checked
from .irf import InstrumentResponse, ResponseError
from .provenance import __version__

__all__ = ["RESPONSE_KIND", "ResponseStoreError", "write_response_group", "read_response_group",
           "save_response", "load_response", "samples_sha256"]

RESPONSE_KIND = "instrument_response"
FORMAT_VERSION = 1
REFERENCE = "t = 0 is the instant a component's delay refers to (streaklab: the response's peak)"


class ResponseStoreError(ResponseError):
    """A path or group does not hold a usable instrument response (says why)."""


def samples_sha256(irf: InstrumentResponse) -> str:
    """sha256 (hex) of the response's samples as little-endian float64: what a result records to
    name the response it was made with, and what a stored copy is checked against."""
    return hashlib.sha256(np.ascontiguousarray(irf.samples, "<f8").tobytes()).hexdigest()


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _attributes(irf: InstrumentResponse) -> dict:
    return {
        "streaklab_kind": RESPONSE_KIND,
        "format_version": FORMAT_VERSION,
        "time_step_ps": irf.time_step_ps,
        "t0_ps": irf.t0_ps,
        "units": "1/ps",
        "normalization": "unit area",
        "reference": REFERENCE,
        "peak_time_ps": irf.peak_time_ps,
        "fwhm_ps": irf.fwhm_ps(),
        "model": irf.model,
        "provenance": irf.provenance,
        "software_version": __version__,
        "created_utc": _utc_now(),
    }


def write_response_group(group: zarr.Group, irf: InstrumentResponse) -> None:
    """Write ``irf`` into an empty Zarr group (arrays ``response`` and ``irf_t`` and the attributes)."""
    attrs = _attributes(irf)
    group.attrs.update(attrs)
    r = create_array(group, "response", shape=(irf.n_samples,), dtype="float64", dimension_names=["irf_t"],
                           attributes={"units": "1/ps", "long_name": "instrument response (unit area)"})
    r[:] = irf.samples
    t = create_array(group, "irf_t", shape=(irf.n_samples,), dtype="float64", dimension_names=["irf_t"],
                           attributes={"units": "ps", "long_name": "time relative to the response's reference instant"})
    t[:] = irf.time_axis_ps()


def _from_parts(samples, attrs: dict, where: str) -> InstrumentResponse:
    if attrs.get("streaklab_kind") != RESPONSE_KIND:
        raise ResponseStoreError(f"{where} is not an instrument response (streaklab_kind = "
                                 f"{attrs.get('streaklab_kind')!r})")
    for key in ("time_step_ps", "t0_ps"):
        if key not in attrs:
            raise ResponseStoreError(f"{where} lacks the {key!r} attribute")
    try:
        return InstrumentResponse(np.asarray(samples, dtype=np.float64), float(attrs["time_step_ps"]),
                                  float(attrs["t0_ps"]), attrs.get("provenance") or {}, attrs.get("model"))
    except ResponseError as exc:
        raise ResponseStoreError(f"{where}: {exc}") from None


def read_response_group(group: zarr.Group, *, where: str = "the group") -> InstrumentResponse:
    """Read a response written by :func:`write_response_group`."""
    if "response" not in group:
        raise ResponseStoreError(f"{where} has no 'response' array")
    return _from_parts(read_checked(group["response"], ..., store=where), dict(group.attrs), where)


def save_response(path, irf: InstrumentResponse, *, overwrite: bool = False, inputs=()) -> Path:
    """Save a response as a standalone Zarr store, or as ``.npz`` when ``path`` ends in ``.npz``.

    Written beside ``path`` and renamed into place; an existing ``path`` needs ``overwrite`` and
    is replaced only when it is a response (or a plain file); ``inputs`` (the stores the
    response was estimated from) are never written over (:func:`core.staging.check_output_path`).
    """
    return save_calibration(path, kind=RESPONSE_KIND, arrays={"response": irf.samples, "irf_t": irf.time_axis_ps()},
                            attributes=_attributes(irf), write_group=lambda g: write_response_group(g, irf),
                            overwrite=overwrite, inputs=inputs)


def load_response(path) -> InstrumentResponse:
    """Read a response from a ``.npz`` file, a response store, or the ``irf`` group of a cube store."""
    found = open_calibration(path, kind=RESPONSE_KIND, group_name="irf", array_names=("response",),
                             error=ResponseStoreError, what="instrument response")
    if found.group is None:
        return _from_parts(found.arrays["response"], found.attributes, found.where)
    return read_response_group(found.group, where=found.where)
