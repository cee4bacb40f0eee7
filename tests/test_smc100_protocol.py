"""Exact bytes on the wire for the SMC100 scan-mirror driver, against a scripted fake on a pty."""
from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest
import serial

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.interfaces import ScanMirror
from drivers.smc100 import SMC100Mirror, decode_positioner_errors, format_value

pytestmark = pytest.mark.timeout(20)


class ScriptedController:
    """The far end of a pty: expects exact command lines, answers canned replies.

    ``script`` is a list of ``(expected_line, reply)``; ``reply`` None means the
    controller stays silent (as it does for setting commands).
    """

    def __init__(self, script):
        self.script = list(script)
        self.received: list[bytes] = []
        self.mismatch = None
        master, slave = os.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        self.master, self.slave = master, slave
        self.port = os.ttyname(slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                buf += os.read(self.master, 1024)
            except OSError:
                return
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                line += b"\n"
                self.received.append(line)
                if not self.script:
                    self.mismatch = (None, line)
                    continue
                expected, reply = self.script.pop(0)
                if line != expected:
                    self.mismatch = (expected, line)
                    continue
                if reply is not None:
                    os.write(self.master, reply)

    def close(self):
        self._stop.set()
        self._thread.join(2)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def scripted():
    fakes = []

    def make(script, **kwargs):
        fake = ScriptedController(script)
        fakes.append(fake)
        return fake, SMC100Mirror(fake.port, timeout_s=0.3, poll_interval_s=0.001, **kwargs)

    yield make
    for fake in fakes:
        fake.close()


def test_driver_implements_the_scan_mirror_interface(scripted):
    fake, mirror = scripted([])
    assert isinstance(mirror, ScanMirror)
    mirror.close()


def test_identify_position_state_bytes(scripted):
    fake, mirror = scripted([
        (b"1ID?\r\n", b"1IDPR50CC_GALVO\r\n"),
        (b"1TP\r\n", b"1TP12.5000\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TS\r\n", b"1TS00000A\r\n"),
        (b"1TS\r\n", b"1TS000128\r\n"),
    ])
    assert mirror.identify() == "PR50CC_GALVO"
    assert mirror.position() == 12.5
    assert mirror.state() == "ready"
    assert mirror.state() == "not_referenced"
    assert mirror.status() == (0x0001, "28")
    mirror.close()
    assert fake.mismatch is None
    assert fake.received == [b"1ID?\r\n", b"1TP\r\n", b"1TS\r\n", b"1TS\r\n", b"1TS\r\n"]


def test_move_sends_pa_then_checks_te(scripted):
    fake, mirror = scripted([
        (b"1PA12.5\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PA-3\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
    ])
    mirror.move_to(12.5)
    mirror.move_to(-3.0)
    mirror.close()
    assert fake.mismatch is None and not fake.script


def test_other_address_is_used_in_every_command(scripted):
    fake, mirror = scripted([(b"12TP\r\n", b"12TP-0.2500\r\n"), (b"12ST\r\n", None)], address=12)
    assert mirror.position() == -0.25
    mirror.stop()
    time.sleep(0.05)
    mirror.close()
    assert fake.mismatch is None and not fake.script


@pytest.mark.parametrize("letter, meaning", [
    ("C", "Parameter missing or out of range."),
    ("H", "Command not allowed in NOT REFERENCED state."),
    ("G", "Displacement out of limits."),
])
def test_te_error_letter_becomes_device_error_with_documented_meaning(scripted, letter, meaning):
    fake, mirror = scripted([(b"1PA99\r\n", None), (b"1TE\r\n", f"1TE{letter}\r\n".encode())])
    with pytest.raises(DeviceError) as info:
        mirror.move_to(99)
    assert info.value.code == letter
    assert info.value.meaning == meaning
    assert info.value.command == "1PA99"
    mirror.close()


def test_home_from_not_referenced_sends_or_and_polls_until_ready(scripted):
    fake, mirror = scripted([
        (b"1TS\r\n", b"1TS00000A\r\n"),
        (b"1OR\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS000032\r\n"),
        (b"1TP\r\n", b"1TP0.0000\r\n"),
    ])
    mirror.home(timeout_s=5)
    mirror.close()
    assert fake.mismatch is None and not fake.script


def test_home_when_already_referenced_moves_to_zero(scripted):
    fake, mirror = scripted([
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1PA0\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000028\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP0.0000\r\n"),
    ])
    mirror.home(timeout_s=5)
    mirror.close()
    assert fake.mismatch is None and not fake.script


def test_wait_settled_returns_final_position(scripted):
    fake, mirror = scripted([
        (b"1TS\r\n", b"1TS000028\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP7.2500\r\n"),
    ])
    assert mirror.wait_settled(timeout_s=5) == 7.25
    mirror.close()


def test_wait_settled_times_out_while_moving(scripted):
    fake, mirror = scripted([(b"1TS\r\n", b"1TS000028\r\n")] * 400)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        mirror.wait_settled(timeout_s=0.2)
    assert time.monotonic() - t0 < 2.0
    mirror.close()


def test_wait_settled_reports_positioner_errors_when_motion_ends_unreferenced(scripted):
    fake, mirror = scripted([(b"1TS\r\n", b"1TS00200F\r\n")])  # following error, NOT REF from MOVING
    with pytest.raises(DeviceError) as info:
        mirror.wait_settled(timeout_s=1)
    assert info.value.code == "0F"
    assert "Following error" in info.value.meaning
    mirror.close()


@pytest.mark.parametrize("reply", [
    b"1TP12.5",            # no terminator before the timeout -> timeout, not a half reply
])
def test_unterminated_reply_times_out(scripted, reply):
    fake, mirror = scripted([(b"1TP\r\n", reply)])
    with pytest.raises(DeviceTimeout):
        mirror.position()
    mirror.close()


@pytest.mark.parametrize("reply", [
    b"1TS12.5\r\n",          # answer to another command
    b"2TP12.5\r\n",          # another controller address
    b"1TPabc\r\n",           # not a number
    b"1TP\xff\xfe\r\n",      # not ASCII
    b"1TP12.5\n",            # LF without CR
])
def test_malformed_replies_raise_protocol_error_with_raw_bytes(scripted, reply):
    fake, mirror = scripted([(b"1TP\r\n", reply)])
    with pytest.raises(ProtocolError) as info:
        mirror.position()
    assert info.value.raw == reply
    mirror.close()


def test_malformed_ts_and_te(scripted):
    fake, mirror = scripted([(b"1TS\r\n", b"1TS0000ZZ\r\n"), (b"1TE\r\n", b"1TE?\r\n")])
    with pytest.raises(ProtocolError):
        mirror.state()
    with pytest.raises(ProtocolError):
        mirror.last_error()
    mirror.close()


def test_context_manager_stops_motion_even_when_the_body_raises(scripted):
    fake, mirror = scripted([(b"1ST\r\n", None)])
    with pytest.raises(RuntimeError):
        with mirror:
            raise RuntimeError("body failed")
    deadline = time.monotonic() + 2
    while not fake.received and time.monotonic() < deadline:
        time.sleep(0.01)
    assert fake.received == [b"1ST\r\n"]
    with pytest.raises(ConnectionLost):
        mirror.position()


def test_works_over_a_pyserial_url():
    # loop:// echoes what is written: the echo is not a valid reply, so the driver says so.
    mirror = SMC100Mirror("loop://", timeout_s=0.2)
    with pytest.raises(ProtocolError) as info:
        mirror.position()
    assert info.value.raw == b"1TP\r\n"
    mirror.close()


def test_unopenable_port_is_connection_lost():
    with pytest.raises(ConnectionLost, match="/dev/does-not-exist"):
        SMC100Mirror("/dev/does-not-exist")


def test_bad_arguments_are_rejected_with_clear_errors(scripted):
    with pytest.raises(ValueError, match="address"):
        SMC100Mirror("loop://", address=0)
    fake, mirror = scripted([])
    with pytest.raises(ValueError, match="finite"):
        mirror.move_to(float("nan"))
    with pytest.raises(ValueError, match="timeout_s"):
        mirror.wait_settled(timeout_s=0)
    mirror.close()
    assert fake.received == []


def test_value_formatting_and_error_bits():
    assert [format_value(v) for v in (12.5, -3.0, 0.0, -0.0, 1e-7, 0.1234567)] == \
        ["12.5", "-3", "0", "0", "0", "0.123457"]
    assert decode_positioner_errors(0x0003) == ["Positive end of run", "Negative end of run"]
    assert decode_positioner_errors(0) == []


def test_serial_settings_are_57600_8n1(scripted):
    fake, mirror = scripted([])
    ser = mirror._serial
    assert (ser.baudrate, ser.bytesize, ser.parity, ser.stopbits) == (57600, 8, serial.PARITY_NONE, 1)
    assert not ser.xonxoff and not ser.rtscts
    mirror.close()
