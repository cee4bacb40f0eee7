"""Documented limits: sizes and waits are refused before anything is allocated or written."""
import numpy as np
import pytest

from core import limits as L
from acquisition.config import parse_config
from acquisition.session import CaptureError, CaptureFailed, CaptureSession
from drivers.errors import DeviceTimeout


def test_check_memory_names_key_and_limit_and_compares_with_available_memory():
    with pytest.raises(L.LimitError, match=r"^camera\.frames_per_line: needs 5\.00 GiB for x, above the limit "
                                           r"of 4\.00 GiB$"):
        L.check_memory("camera.frames_per_line", 5 << 30, 4 << 30, what="for x")
    with pytest.raises(L.LimitError, match=r"^k: needs 3\.00 GiB, but only 1\.00 GiB of memory is available$"):
        L.check_memory("k", 3 << 30, 4 << 30, memory=1 << 30)
    assert L.check_memory("k", 1 << 20, 4 << 30, memory=1 << 30) == 1 << 20
    avail = L.available_memory()
    assert avail is not None and 0 < avail
    with pytest.raises(L.LimitError, match="of memory is available"):
        L.check_memory("k", avail + (1 << 30), avail + (2 << 30))


def test_backoff_waits_are_capped():
    assert L.backoff_waits(4, 0.5) == [0.5, 1.0, 2.0, 4.0]
    waits = L.backoff_waits(100, 0.5)       # 0.5 * 2**35 s would overflow time.sleep
    assert max(waits) == L.MAX_BACKOFF_WAIT_S and waits[7:] == [60.0] * 93


class _Camera:
    def __init__(self, shape):
        self.shape, self.acquired = shape, 0

    def identify(self):
        return "fake camera"

    def configure(self, **kw):
        pass

    def acquire(self, timeout_s):
        self.acquired += 1
        return type("Image", (), {"data": np.zeros(self.shape, np.uint16)})()

    def stop(self):
        pass


class _Mirror:
    def identify(self):
        return "fake mirror"

    def state(self):
        return "ready"

    def home(self, timeout_s):
        pass


class _Sync:
    def identify(self):
        return "fake sync"

    def set_output(self, on):
        pass

    def read_errors(self):
        return []

    def set_repetition_rate(self, hz):
        pass

    def set_trigger_delay(self, ps, channel=None):
        pass


def _config(**sections):
    raw = {"scan": {"angles_deg": [0.0, 1.0]}, "calibration": {"time_poly_ps": [0.0, 2.0]}}
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    return parse_config(raw)


def test_retry_waits_are_capped_each_and_in_all(tmp_path):
    waits = []
    session = CaptureSession(_config(session={"retries": 12, "retry_backoff_s": 0.5}), tmp_path / "r.zarr",
                             _Camera((4, 4)), _Mirror(), _Sync(), sleep=waits.append)

    def timeout():
        raise DeviceTimeout("no reply")

    with pytest.raises(CaptureFailed, match="failed after 13 attempts"):
        session._attempt("step", timeout)
    assert waits == [0.5, 1, 2, 4, 8, 16, 32, 60, 60, 60, 60, 60]       # 423.5 s, not 0.5 * (2**12 - 1)
    waits.clear()
    session.retries = 100                                              # beyond what the config allows
    with pytest.raises(CaptureFailed, match="failed after 101 attempts"):
        session._attempt("step", timeout)
    assert max(waits) == 60 and sum(waits) == L.MAX_BACKOFF_TOTAL_S


@pytest.mark.parametrize("sections, key", [({"camera": {"frames_per_line": 10000}}, "camera.frames_per_line"),
                                           ({"dark": {"frames": 10000}}, "dark.frames")])
def test_frames_that_cannot_fit_in_memory_are_refused_after_the_first_frame(tmp_path, sections, key):
    # 10000 frames of 4096 x 4096 uint16 = 312.5 GiB (twice that with the stacked copy)
    camera = _Camera((4096, 4096))
    session = CaptureSession(_config(**sections), tmp_path / "r.zarr", camera, _Mirror(), _Sync())
    with pytest.raises(CaptureError, match=rf"^{key}: needs 625\.00 GiB for 10000 frames of 4096 x 4096 pixels "
                                           r"\(limits\.MAX_LINE_BYTES\), above the limit of 4\.00 GiB; take fewer"):
        session.run()
    assert camera.acquired == 1 and not (tmp_path / "r.zarr").exists()


def test_a_time_bin_too_fine_for_the_cube_is_refused_before_any_line(tmp_path):
    # 32 rows of 2 ps: a 62 ps window; 1e-6 ps bins would make 6.2e7 bins in the cube
    session = CaptureSession(_config(calibration={"time_bin_ps": 1e-6}), tmp_path / "r.zarr", _Camera((4, 32)),
                             _Mirror(), _Sync())
    with pytest.raises(CaptureError, match=r"^calibration\.time_bin_ps = 1e-06 ps makes 6\.2e\+07 time bins of "
                                           r"the calibrated window of 62 ps, above the limit of 65536 bins"):
        session.run()
    assert not (tmp_path / "r.zarr").exists()
