"""RemoteEx driver: exact bytes on both ports, in memory (no socket, no thread, no sleep)."""
import logging

import numpy as np
import pytest

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.logutil import WarningLimiter
from drivers.remoteex_wire import normalize_time_range, scaling_table_unit_ps, time_range_seconds

from _remoteex_script import scripted_camera, scripted_link

pytestmark = pytest.mark.timeout(20)


def test_both_ports_are_opened_before_either_greeting_is_read():
    order = []
    open_transports, cmd, data = scripted_link([(b"AcqStatus()\r", b"0,AcqStatus,idle\r")])
    real_read = {cmd: cmd.read_line, data: data.read_line}

    def watch(t, which):
        def read_line(timeout_s=None):
            order.append(which)
            return real_read[t](timeout_s)
        return read_line

    cmd.read_line, data.read_line = watch(cmd, "command"), watch(data, "data")

    def opening(timeout_s):
        order.append("open both")
        return open_transports(timeout_s)

    from drivers.remoteex import RemoteExCamera
    cam = RemoteExCamera("127.0.0.1", 1001, start_app=False, open_transports=opening)
    assert order[:3] == ["open both", "command", "data"]
    assert cam.acq_status() == ("idle", "")
    cam.close()
    cmd.assert_done()


def test_wrong_greeting_is_a_protocol_error_naming_the_port():
    open_transports, cmd, data = scripted_link([], data_banner=b"Hello\r")
    from drivers.remoteex import RemoteExCamera
    with pytest.raises(ProtocolError, match="data port") as info:
        RemoteExCamera("127.0.0.1", 1001, start_app=False, open_transports=open_transports)
    assert info.value.raw == b"Hello\r"


def test_stray_bytes_on_the_data_port_are_discarded_before_a_transfer(caplog):
    pixels = np.array([[1, 2, 3], [4, 5, 6]], dtype="<u2")
    cam, cmd, data = scripted_camera([
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
        (b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,3,2,2,Data\r", pixels.tobytes()),
    ])
    assert cam.acq_status()[0] == "idle"
    data.feed(b"\x01\x01\x01")                 # e.g. the tail of an earlier, interrupted transfer
    with caplog.at_level(logging.WARNING, logger="drivers.remoteex"):
        img = cam.read_image()
    np.testing.assert_array_equal(img, pixels.T)     # not 257 (0x0101) in the first pixels, not shifted
    assert cam.stray_data_bytes == 3
    assert "discarded 3 stray bytes" in caplog.text
    cam.close()
    cmd.assert_done()


def test_bytes_beyond_the_announced_count_refuse_the_transfer():
    cam, cmd, data = scripted_camera([
        (b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,2,1,2,Data\r", b"\x07\x00\x08\x00\x09"),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
    ])
    with pytest.raises(ProtocolError, match="1 bytes beyond the 4 announced"):
        cam.read_image()
    with pytest.raises(ConnectionLost):        # the link was closed; this script cannot reopen it
        cam.acq_status()


def test_a_server_repeating_replies_for_another_command_logs_a_few_warnings_not_thousands(caplog):
    flood = b"0,CamParamGet,10 ms\r" * 5000
    cam, cmd, data = scripted_camera([(b"AcqStatus()\r", flood + b"0,AcqStatus,idle\r")])
    with caplog.at_level(logging.WARNING, logger="drivers.remoteex"):
        assert cam.acq_status() == ("idle", "")
    skipped = [r for r in caplog.records if "skipping reply" in r.getMessage()]
    assert 1 <= len(skipped) <= 2
    assert cam._warnings.counts["foreign-reply"] == 5000
    cam.close()
    cmd.assert_done()


def test_warning_limiter_reports_what_it_suppressed(caplog):
    now = [0.0]
    limiter = WarningLimiter(logging.getLogger("limiter-test"), interval_s=5.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="limiter-test"):
        for t in (0.0, 1.0, 2.0, 6.0):
            now[0] = t
            limiter.warning("k", "fault %d", 7)
        limiter.warning("other", "another fault")
    messages = [r.getMessage() for r in caplog.records]
    assert messages == ["fault 7", "fault 7 (2 similar messages suppressed in the last 6 s)", "another fault"]
    with pytest.raises(ValueError):
        WarningLimiter(logging.getLogger("x"), interval_s=0)


def test_time_range_strings_and_setting_numbers_on_the_wire():
    cam, cmd, data = scripted_camera([
        (b"DevParamSet(Streak,Time Range,1 ns)\r", b"0,DevParamSet\r"),
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,2 ns\r"),
        (b"DevParamSet(Streak,Time Range,3)\r", b"0,DevParamSet\r"),
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,4\r"),
    ])
    cam.configure(time_range="1ns")
    assert cam.time_range() == "2 ns"
    cam.configure(time_range=3)
    assert cam.time_range() == 4
    for bad in (2.5, "fast", "-1 ns", True):
        with pytest.raises(ValueError, match="time"):
            cam.configure(time_range=bad)
    cam.close()
    cmd.assert_done()


def test_time_range_helpers():
    assert normalize_time_range("500ps") == "500 ps" and normalize_time_range(" 2 ") == 2
    assert time_range_seconds("1 ns") == pytest.approx(1e-9) and time_range_seconds(2) is None
    assert scaling_table_unit_ps("500 ps") == 1.0 and scaling_table_unit_ps("20 ns") == pytest.approx(1e3)
    assert scaling_table_unit_ps("1 us") == pytest.approx(1e6) and scaling_table_unit_ps(3) is None


def test_scaling_table_is_read_from_the_data_port_and_converted_to_ps():
    table = np.array([0.01, 0.2, 0.4, 0.625], dtype="<f4")     # ns, as the "1 ns" range writes it
    cam, cmd, data = scripted_camera([
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,1 ns\r"),
        (b"ImgDataGet(Current,ScalingTable,Vertical)\r", b"0,ImgDataGet,4,ScalingTable\r", table.tobytes()),
        (b"ImgDataGet(Current,ScalingTable,Vertical)\r", b"7,ImgDataGet\r"),
        (b"ImgDataGet(Current,ScalingTable,Vertical)\r", b"8,ImgDataGet\r"),
    ], synchroscan_table_unit_ps=1.0)
    np.testing.assert_allclose(cam.scaling_table_ps(), [10.0, 200.0, 400.0, 625.0], rtol=1e-6)
    assert cam.scaling_table_ps() is None               # 7: this image has no table scaling
    with pytest.raises(DeviceError) as info:
        cam.scaling_table_ps()                          # any other code is an error
    assert info.value.code == 8
    cam.close()
    cmd.assert_done()


def test_camera_info_collects_the_extra_lines_of_its_reply():
    cam, cmd, data = scripted_camera([
        (b"CamParamGet(Setup,CameraInfo)\r",
         b"0,CamParamGet,OrcaFlash 4.0 V3\r\nProduct number: C13440-20C\r\nSerial number: 301730\r\n"
         b"Firmware: 4.20.B\r\nVersion: 4.20.B03\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
    ])
    assert cam.camera_info() == ["OrcaFlash 4.0 V3", "Product number: C13440-20C", "Serial number: 301730",
                                 "Firmware: 4.20.B", "Version: 4.20.B03"]
    assert cam.acq_status()[0] == "idle"
    cam.close()
    cmd.assert_done()


def test_extra_reply_lines_nobody_asked_for_are_skipped():
    cam, cmd, data = scripted_camera([
        (b"CamParamGet(Setup,CameraInfo)\r", b"0,CamParamGet,Orca\r\nProduct number: 1\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,busy,Live\r"),
    ])
    assert cam.command("CamParamGet", "Setup", "CameraInfo") == ["Orca"]
    assert cam.acq_status() == ("busy", "Live")
    cam.close()
    cmd.assert_done()


def test_live_mode_takes_the_newest_announced_image_from_the_ring_buffer():
    pixels = np.array([[10, 20], [30, 40], [50, 60]], dtype="<u2")           # 2 columns (x), 3 rows (t)
    cam, cmd, data = scripted_camera([
        (b"AcqLiveMonitor(RingBuffer,4)\r", b"0,AcqLiveMonitor\r"),
        (b"AcqStart(Live)\r", b"0,AcqStart\r4,Livemonitor,RingBuffer,1\r4,Livemonitor,RingBuffer,2\r"),
        (b"ImgRingBufferGet(Data,2)\r", b"0,ImgRingBufferGet,2,3,2,Data,2,1500\r", pixels.tobytes()),
        (b"AcqStop()\r", b"4,Livemonitor,RingBuffer,3\r0,AcqStop\r"),
        (b"AcqLiveMonitor(Off)\r", b"0,AcqLiveMonitor\r"),
    ])
    cam.start_live(ring_buffers=4)
    img, seq = cam.live_image(timeout_s=1.0)
    assert seq == 2
    np.testing.assert_array_equal(img, pixels.T)
    cam.stop_live()
    assert not cam.live_events                          # an announcement that raced the stop is dropped
    with pytest.raises(DeviceTimeout, match="no live image"):
        cam.wait_live_event(0.01)
    cam.close()
    cmd.assert_done()


def test_streak_mode_focus_and_operate():
    cam, cmd, data = scripted_camera([
        (b"DevParamSet(Streak,MCP Gain,0)\r", b"0,DevParamSet\r"),         # the focus-mode gain interlock
        (b"DevParamSet(Streak,Mode,Focus)\r", b"0,DevParamSet\r"),
        (b"DevParamGet(Streak,Mode)\r", b"0,DevParamGet,Focus\r"),
    ])
    cam.set_streak_mode("Focus")
    assert cam.streak_mode() == "Focus"
    with pytest.raises(ValueError, match="Operate"):
        cam.set_streak_mode("Sweep")
    cam.close()
    cmd.assert_done()


def test_acquire_in_memory_with_a_notification_and_a_foreign_reply():
    pixels = np.arange(6, dtype="<u2").reshape(2, 3)
    cam, cmd, data = scripted_camera([
        (b"AcqStart(Acquire)\r", b"0,AcqStart\r"),
        (b"AcqStatus()\r", b"5,Message,hello\r0,AcqStatus,busy,Acquire\r"),
        (b"AcqStatus()\r", b"0,AcqStatus,idle\r"),
        (b"ImgDataGet(Current,Data)\r", b"0,ImgDataGet,3,2,2,Data\r", pixels.tobytes()),
        (b"DevParamGet(Streak,Time Range)\r", b"0,DevParamGet,500 ps\r"),
        (b"CamParamGet(Acquire,Exposure)\r", b"0,CamParamGet,10 ms\r"),
        (b"DevParamGet(Streak,MCP Gain)\r", b"0,DevParamGet,20\r"),
        (b"DevParamGet(Delaybox,Delay A)\r", b"0,DevParamGet,0\r"),
    ])
    img = cam.acquire(timeout_s=2.0)
    np.testing.assert_array_equal(img.data, pixels.T)
    assert img.metadata["time_range"] == "500 ps" and img.metadata["gain"] == 20
    cam.close()
    cmd.assert_done()


def test_a_dropped_link_reopens_both_ports_reads_both_greetings_and_resends_the_command():
    from drivers.remoteex import RemoteExCamera

    first = scripted_link([(b"AcqStatus()\r", ConnectionResetError("peer reset"))])
    second = scripted_link([(b"AcqStatus()\r", b"0,AcqStatus,idle\r")])
    pairs = [first, second]

    def open_transports(timeout_s):
        if not pairs:
            raise ConnectionLost("no more links")
        opener, _, _ = pairs.pop(0)
        return opener(timeout_s)

    cam = RemoteExCamera("127.0.0.1", 1001, start_app=False, open_transports=open_transports)
    assert cam.acq_status() == ("idle", "")
    assert cam.reconnects == 1 and first[1].closed and first[2].closed
    cam.close()
    second[1].assert_done()
    with pytest.raises(ConnectionLost):
        cam.acq_status()
