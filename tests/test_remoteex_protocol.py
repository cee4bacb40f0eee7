"""RemoteEx driver: exact bytes on the wire.

Each test gives a script of (expected command bytes, canned reply bytes,
data-port bytes); every command must match byte for byte, in order, and the
test fails if the driver sent anything else or left a step unsent.  Most tests
run in memory (``scripted_camera`` of ``tests/_remoteex_script.py``: no socket,
no thread, no sleep).  The tests that use ``ScriptedServer`` are the
integration tier: the same kind of script through a loopback TCP server, for
what only real sockets show (replies split across packets, real timeouts, a
closed connection, refused connections).
"""
import socket
import threading
import time

import numpy as np
import pytest

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.interfaces import StreakCamera
from drivers.remoteex import (
    COMMAND_BANNER, DATA_BANNER, ERROR_MEANINGS, RemoteExCamera, format_command, format_exposure,
    format_seconds, parse_exposure, parse_reply,
)
from drivers.sim.camera import bind_port_pair

from _remoteex_script import scripted_camera

pytestmark = pytest.mark.timeout(20)


class ScriptedServer:
    """A RemoteEx stand-in that checks each command against a script.

    script: list of ``(expected, reply)`` or ``(expected, reply, data)``; ``reply``
    may be a list of byte chunks sent with a short pause between them.
    """

    def __init__(self, script, *, banner=COMMAND_BANNER, data_banner=DATA_BANNER):
        self.script = [tuple(s) + (b"",) * (3 - len(s)) for s in script]
        self.banner, self.data_banner = banner, data_banner
        self.cmd_l, self.data_l = bind_port_pair()
        self.port = self.cmd_l.getsockname()[1]
        self.errors = []
        self.received = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _readline(self, conn, buf):
        while b"\r" not in buf:
            chunk = conn.recv(4096)
            if not chunk:
                return None, buf
            buf += chunk
        i = buf.index(b"\r")
        return bytes(buf[: i + 1]), buf[i + 1:]

    def _run(self):
        conn = data = None
        try:
            self.cmd_l.settimeout(10)
            self.data_l.settimeout(10)
            conn, _ = self.cmd_l.accept()
            conn.settimeout(10)
            conn.sendall(self.banner)
            if self.banner != COMMAND_BANNER:
                conn.recv(1)
                return
            data, _ = self.data_l.accept()
            data.sendall(self.data_banner)
            buf = b""
            for expected, reply, payload in self.script:
                line, buf = self._readline(conn, buf)
                self.received.append(line)
                if line != expected:
                    self.errors.append(f"expected {expected!r}, got {line!r}")
                    return
                for chunk in (reply if isinstance(reply, list) else [reply]):
                    conn.sendall(chunk)
                    if isinstance(reply, list):
                        time.sleep(0.02)
                if payload:
                    data.sendall(payload)
            line, buf = self._readline(conn, buf)     # nothing more may arrive until the client closes
            if line is not None:
                self.errors.append(f"unexpected extra command {line!r}")
        except Exception as exc:  # noqa: BLE001 - reported to the test
            self.errors.append(f"server: {exc!r}")
        finally:
            for s in (conn, data, self.cmd_l, self.data_l):
                if s is not None:
                    s.close()
            self.done.set()

    def check(self):
        assert self.done.wait(10), "scripted server still waiting"
        assert not self.errors, self.errors
        assert len(self.received) == len(self.script)


def camera(server, **kw):
    kw.setdefault("start_app", False)
    kw.setdefault("timeout_s", 2.0)
    return RemoteExCamera("127.0.0.1", server.port, **kw)


def test_implements_streak_camera_interface():
    assert issubclass(RemoteExCamera, StreakCamera)


def test_connect_sends_app_start_and_exact_setting_commands():
    cam, srv, _data = scripted_camera([
        (b"AppStart()\r", b"0,AppStart\r"),
        (b"DevParamSet(Streak,Time Range,3)\r", b"0,DevParamSet\r"),
        (b"CamParamSet(Acquire,Exposure,12.5 ms)\r", b"0,CamParamSet\r"),
        (b"DevParamSet(Streak,MCP Gain,12)\r", b"0,DevParamSet\r"),
        (b"DevParamSet(Delaybox,Delay A,0.00000000015)\r", b"0,DevParamSet\r"),
        (b"CamParamGet(Acquire,Exposure)\r", b"0,CamParamGet,12.5 ms\r"),
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,3\r"),
        (b"DevParamGet(Streak,MCP Gain)\r", b"0,DevParamGet,12\r"),
        (b"DevParamGet(Delaybox,Delay A)\r", b"0,DevParamGet,0.00000000015\r"),
        (b"AppInfo(Type)\r", b"0,AppInfo,HPD-TA\r"),
        (b"AppInfo(Version)\r", b"0,AppInfo,9.5 pf3\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,busy,Acquire\r"),
        (b"AcqStop()\r", b"0,AcqStop\r"),
        (b"AppEnd()\r", b"0,AppEnd\r"),
    ], start_app=True)
    cam.configure(time_range=3, exposure_s=0.0125, gain=12)
    cam.set_delay_ps(150.0)
    assert cam.exposure_s() == pytest.approx(0.0125)
    assert cam.time_range() == 3
    assert cam.gain() == 12
    assert cam.delay_ps() == pytest.approx(150.0)
    assert cam.identify().startswith("Hamamatsu HPD-TA 9.5 pf3")
    assert cam.acq_status() == ("busy", "Acquire")
    cam.stop()
    cam.app_end()
    cam.close()
    srv.assert_done()


def test_acquire_sequence_and_pixel_layout():
    # 3 columns (slit, x) by 2 rows (sweep, t), little-endian uint16, row-major.
    pixels = np.array([[1, 2, 3], [256, 513, 65535]], dtype="<u2")
    cam, srv, _data = scripted_camera([
        (b"DevParamSet(Streak,Time Range,2)\r", b"0,DevParamSet\r"),
        (b"CamParamSet(Acquire,Exposure,10 ms)\r", b"0,CamParamSet\r"),
        (b"DevParamSet(Streak,MCP Gain,30)\r", b"0,DevParamSet\r"),
        (b"DevParamSet(Delaybox,Delay A,0)\r", b"0,DevParamSet\r"),
        (b"AcqStart(Acquire)\r", b"0,AcqStart\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,busy,Acquire\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
        (b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,3,2,2,Data\r", pixels.tobytes()),
    ])
    cam.configure(time_range=2, exposure_s=0.01, gain=30)
    cam.set_delay_ps(0)
    img = cam.acquire(timeout_s=5)
    cam.close()
    srv.assert_done()
    assert img.data.dtype == np.uint16 and img.data.shape == (3, 2)
    np.testing.assert_array_equal(img.data, pixels.T)
    assert img.metadata["time_range"] == 2 and img.metadata["exposure_s"] == pytest.approx(0.01)
    assert img.metadata["gain"] == 30 and img.metadata["delay_ps"] == 0.0


def test_acquire_reads_settings_it_does_not_know_and_tolerates_missing_delay_generator():
    cam, srv, _data = scripted_camera([
        (b"AcqStart(Acquire)\r", b"0,AcqStart\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
        (b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,1,1,2,Data\r", b"\x07\x00"),
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,4\r"),
        (b"CamParamGet(Acquire,Exposure)\r", b"0,CamParamGet,2 s\r"),
        (b"DevParamGet(Streak,MCP Gain)\r", b"0,DevParamGet,5\r"),
        (b"DevParamGet(Delaybox,Delay A)\r", b"2,DevParamGet\r"),
    ])
    img = cam.acquire()
    cam.close()
    srv.assert_done()
    assert img.data.tolist() == [[7]]
    assert img.metadata["time_range"] == 4 and img.metadata["exposure_s"] == 2.0
    assert img.metadata["gain"] == 5 and img.metadata["delay_ps"] is None


@pytest.mark.parametrize("bpp,dtype", [(1, "<u1"), (4, "<u4")])
def test_other_pixel_depths_are_converted_to_uint16(bpp, dtype):
    pixels = np.array([[0, 9], [200, 255]], dtype=dtype)
    cam, srv, _data = scripted_camera([(b"ImgDataGet(Current,Data)\r", f"0,ImgDataGet,2,2,{bpp},Data\r".encode(),
                                        pixels.tobytes())])
    out = cam.read_image()
    cam.close()
    srv.assert_done()
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, pixels.T)


def test_unsolicited_notifications_between_command_and_reply_are_skipped():
    srv = ScriptedServer([
        # Code 4/5 messages, one of them even naming the command being waited for.
        (b"AcqStatus()\r", b"4,Livemonitor,17\r5,AcqStatus,busy\r0,AcqStatus,idle\r"),
        (b"CamParamGet(Acquire,Exposure)\r", [b"5,Mess", b"age,hello\r4,Livemonitor,18\r0,CamPa", b"ramGet,3 ms\r"]),
    ])
    cam = camera(srv)
    assert cam.acq_status() == ("idle", "")
    assert cam.exposure_s() == pytest.approx(0.003)
    cam.close()
    srv.check()


def test_reply_names_are_matched_case_insensitively_and_foreign_replies_skipped():
    cam, srv, _data = scripted_camera([
        (b"AcqStatus()\r", b"0,CamParamGet,stale\r0,acqstatus,idle\r"),
    ])
    assert cam.acq_status()[0] == "idle"
    cam.close()
    srv.assert_done()


@pytest.mark.parametrize("code", sorted(ERROR_MEANINGS))
def test_error_codes_become_device_errors_and_connection_stays_usable(code):
    cam, srv, _data = scripted_camera([
        (b"CamParamSet(Acquire,Exposure,20 s)\r", f"{code},CamParamSet\r".encode()),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
    ])
    with pytest.raises(DeviceError) as info:
        cam.configure(exposure_s=20.0)
    assert info.value.code == code
    assert info.value.meaning == ERROR_MEANINGS[code]
    assert "CamParamSet(Acquire,Exposure,20 s)" in str(info.value)
    assert cam.acq_status()[0] == "idle"
    cam.close()
    srv.assert_done()


def test_failed_app_start_closes_the_connection():
    srv = ScriptedServer([(b"AppStart()\r", b"8,AppStart\r")])
    with pytest.raises(DeviceError) as info:
        camera(srv, start_app=True)
    assert info.value.code == 8
    srv.check()     # the server saw the connection closed right after the failure


def test_garbage_reply_is_a_protocol_error_with_the_raw_bytes():
    cam, srv, _data = scripted_camera([(b"AcqStatus()\r", b"\xff\xfenot remoteex\r")])
    with pytest.raises(ProtocolError) as info:
        cam.acq_status()
    assert info.value.raw == b"\xff\xfenot remoteex"
    cam.close()
    srv.assert_done()


def test_wrong_banner_is_a_protocol_error():
    srv = ScriptedServer([], banner=b"Hello there\r")
    with pytest.raises(ProtocolError) as info:
        camera(srv)
    assert info.value.raw == b"Hello there\r"
    srv.done.wait(5)


def test_missing_reply_times_out_within_its_timeout():
    srv = ScriptedServer([(b"AcqStatus()\r", b"")])
    cam = camera(srv, timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        cam.acq_status()
    assert time.monotonic() - t0 < 2.0
    cam.close()
    srv.check()


def test_short_image_data_times_out():
    srv = ScriptedServer([(b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,10,10,2,Data\r", b"\x00" * 50)])
    cam = camera(srv, timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="50 of 200"):
        cam.read_image()
    assert time.monotonic() - t0 < 2.0
    cam.close()
    srv.check()


@pytest.mark.parametrize("reply", [b"0,ImgDataGet,10,10\r", b"0,ImgDataGet,10,10,3,Data\r", b"0,ImgDataGet,-1,5,2,Data\r"])
def test_impossible_image_header_is_a_protocol_error(reply):
    cam, srv, _data = scripted_camera([(b"ImgDataGet(Current,Data)\r", reply)])
    with pytest.raises(ProtocolError):
        cam.read_image()
    cam.close()
    srv.assert_done()


def test_exit_stops_acquisition_even_when_the_body_raised():
    cam, srv, _data = scripted_camera([
        (b"AcqStart(Acquire)\r", b"0,AcqStart\r"),
        (b"AcqStop()\r", b"0,AcqStop\r"),
        (b"DevParamSet(Streak,MCP Gain,0)\r", b"0,DevParamSet\r"),
    ])
    with pytest.raises(RuntimeError, match="body failed"):
        with cam:
            cam.start()
            raise RuntimeError("body failed")
    srv.assert_done()
    with pytest.raises(ConnectionLost):
        cam.acq_status()   # closed on exit


def test_connection_refused_is_connection_lost():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(ConnectionLost):
        RemoteExCamera("127.0.0.1", port, connect_timeout_s=1.0)


def test_wire_format_helpers():
    assert format_command("ImgDataGet", "Current", "Data") == b"ImgDataGet(Current,Data)\r"
    assert format_command("AcqStatus") == b"AcqStatus()\r"
    for bad in ("a,b", "x(", "y)", "line\r", "é"):
        with pytest.raises(ValueError):
            format_command("CamParamSet", "Acquire", bad)
    with pytest.raises(ValueError):
        format_command("Bad Name")
    assert parse_reply(b"0,AcqStatus,busy,Acquire") == (0, "AcqStatus", ["busy", "Acquire"])
    assert parse_reply(b"10,CamParamSet") == (10, "CamParamSet", [])
    for bad in (b"", b"0", b"x,AcqStatus", b"0,", b"\xff,AcqStatus"):
        with pytest.raises(ProtocolError):
            parse_reply(bad)
    assert format_exposure(0.0125) == "12.5 ms"
    assert format_exposure(2) == "2 s"
    assert format_exposure(1e-3) == "1 ms"
    assert format_exposure(5e-7) == "500 ns"
    for text, value in (("10 ms", 0.01), ("5ms", 0.005), ("1 s", 1.0), ("1h", 3600.0), ("250 us", 2.5e-4),
                        ("7", 0.007)):
        assert parse_exposure(text) == pytest.approx(value)
    for v in (1e-9, 3.3e-5, 0.0125, 0.999, 1.0, 7.25):
        assert parse_exposure(format_exposure(v)) == pytest.approx(v, rel=1e-6)
    with pytest.raises(ValueError):
        parse_exposure("10 parsecs")
    with pytest.raises(ValueError):
        format_exposure(0)
    assert format_seconds(1.5e-10) == "0.00000000015"
    assert format_seconds(0.0) == "0"
    assert float(format_seconds(2.5e-9)) == pytest.approx(2.5e-9)


def test_bad_arguments_are_rejected_before_anything_is_sent():
    cam, srv, _data = scripted_camera([])
    with pytest.raises(ValueError, match="time_range"):
        cam.configure(time_range=2.5)
    with pytest.raises(ValueError, match="time_range"):
        cam.configure(time_range=True)
    with pytest.raises(ValueError, match="exposure_s"):
        cam.configure(exposure_s=-1)
    with pytest.raises(ValueError, match="gain"):
        cam.configure(gain=-3)
    with pytest.raises(ValueError, match="delay_ps"):
        cam.set_delay_ps(float("nan"))
    with pytest.raises(ValueError, match="timeout_s"):
        cam.acquire(timeout_s=0)
    cam.close()
    srv.assert_done()
