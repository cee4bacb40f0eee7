"""Exact bytes on the wire for the SMC100 scan-mirror driver.

In-memory tier: the driver over a :class:`ScriptedTransport` (no thread, socket
or sleep).  Integration tier at the end: the real serial transport on a pty.
"""
from __future__ import annotations

import os
import termios
import tty

import pytest

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.interfaces import ScanMirror
from drivers.smc100 import COMMANDS, SMC100Mirror, decode_positioner_errors, format_value
from drivers.transport import ScriptedTransport

pytestmark = pytest.mark.timeout(20)


def scripted(script, **kwargs):
    transport = ScriptedTransport(script, timeout_s=0.3)
    return transport, SMC100Mirror(transport=transport, poll_interval_s=1e-4, **kwargs)


def test_driver_implements_the_scan_mirror_interface():
    t, mirror = scripted([])
    assert isinstance(mirror, ScanMirror)
    mirror.close()
    t.assert_done()


def test_identify_position_state_bytes():
    t, mirror = scripted([
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
    t.assert_done()


def test_the_other_queries_in_the_command_table():
    t, mirror = scripted([
        (b"1PA?\r\n", b"1PA7.5\r\n"),
        (b"1TH\r\n", b"1TH3.25\r\n"),
        (b"1VA?\r\n", b"1VA100\r\n"),
        (b"1AC?\r\n", b"1AC400\r\n"),
        (b"1SL?\r\n", b"1SL-45\r\n"),
        (b"1SR?\r\n", b"1SR45\r\n"),
        (b"1VE\r\n", b"1VE SMC_CC - Version 3.0.1\r\n"),
    ])
    assert mirror.target_position() == 7.5
    assert mirror.setpoint_position() == 3.25
    assert mirror.velocity() == 100.0
    assert mirror.acceleration() == 400.0
    assert mirror.travel_limits() == (-45.0, 45.0)
    assert mirror.version() == "SMC_CC - Version 3.0.1"
    t.assert_done()
    assert {n for n, c in COMMANDS.items() if c.checked} == {"PA", "PR", "OR", "MM"}


def test_settings_send_then_check_te():
    t, mirror = scripted([
        (b"1PA12.5\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PA-3\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PR0.25\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1MM0\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1MM1\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1RS\r\n", None),
        (b"1ST\r\n", None),
    ])
    mirror.move_to(12.5)
    mirror.move_to(-3.0)
    mirror.move_by(0.25)
    mirror.enable(False)
    mirror.enable(True)
    mirror.reset()
    mirror.stop()
    t.assert_done()


def test_other_address_is_used_in_every_command():
    t, mirror = scripted([(b"12TP\r\n", b"12TP-0.2500\r\n"), (b"12ST\r\n", None)], address=12)
    assert mirror.position() == -0.25
    mirror.stop()
    t.assert_done()


@pytest.mark.parametrize("letter, meaning", [
    ("C", "Parameter missing or out of range."),
    ("H", "Command not allowed in NOT REFERENCED state."),
    ("G", "Displacement out of limits."),
])
def test_te_error_letter_becomes_device_error_with_documented_meaning(letter, meaning):
    t, mirror = scripted([(b"1PA99\r\n", None), (b"1TE\r\n", f"1TE{letter}\r\n".encode())])
    with pytest.raises(DeviceError) as info:
        mirror.move_to(99)
    assert info.value.code == letter
    assert info.value.meaning == meaning
    assert info.value.command == "1PA99"
    t.assert_done()


def test_home_from_not_referenced_sends_or_and_polls_until_ready():
    t, mirror = scripted([
        (b"1TS\r\n", b"1TS00000A\r\n"),
        (b"1OR\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS000032\r\n"),
        (b"1TP\r\n", b"1TP0.0000\r\n"),
    ])
    mirror.home(timeout_s=5)
    t.assert_done()


def test_home_when_already_referenced_moves_to_zero():
    t, mirror = scripted([
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1PA0\r\n", None),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000028\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP0.0000\r\n"),
        (b"1PA?\r\n", b"1PA0.000000\r\n"),
    ])
    mirror.home(timeout_s=5)
    t.assert_done()


def test_home_when_disabled_leaves_disable_then_moves_to_zero():
    t, mirror = scripted([
        (b"1TS\r\n", b"1TS00003C\r\n"),
        (b"1MM1\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PA0\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP0\r\n"),
        (b"1PA?\r\n", b"1PA0\r\n"),
    ])
    mirror.home(timeout_s=5)
    t.assert_done()


def test_wait_settled_returns_final_position():
    t, mirror = scripted([
        (b"1TS\r\n", b"1TS000028\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP7.2500\r\n"),
    ])
    assert mirror.wait_settled(timeout_s=5) == 7.25
    t.assert_done()


def test_a_move_lost_with_a_reconnect_is_detected_when_settled():
    # PA goes out, the link drops before the controller took it; TE on the reopened link says "@".
    t, mirror = scripted([
        (b"1PA12.5\r\n", None),
        (b"1TE\r\n", OSError(5, "Input/output error")), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP3\r\n"),
        (b"1PA?\r\n", b"1PA3.000000\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"), (b"1TP\r\n", b"1TP3\r\n"),   # no target check any more
    ])
    mirror.move_to(12.5)
    with pytest.raises(DeviceError, match="target is 3 deg, not the 12.5 deg sent") as info:
        mirror.wait_settled(timeout_s=1)
    assert info.value.code == "target"
    assert mirror.wait_settled(timeout_s=1) == 3.0
    t.assert_done()


def test_move_then_wait_settled_checks_the_target_once():
    t, mirror = scripted([
        (b"1PA-2.25\r\n", None), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"), (b"1TP\r\n", b"1TP-2.25\r\n"),
        (b"1PA?\r\n", b"1PA-2.250000\r\n"),
    ])
    mirror.move_to(-2.25)
    assert mirror.wait_settled(timeout_s=1) == -2.25
    t.assert_done()


def test_wait_settled_times_out_while_moving():
    t, mirror = scripted([(b"1TS\r\n", b"1TS000028\r\n")] * 5000)
    with pytest.raises(DeviceTimeout, match="motion not finished within 0.02 s"):
        mirror.wait_settled(timeout_s=0.02)


def test_wait_settled_reports_positioner_errors_when_motion_ends_unreferenced():
    t, mirror = scripted([(b"1TS\r\n", b"1TS00200F\r\n")])  # following error, NOT REF from MOVING
    with pytest.raises(DeviceError) as info:
        mirror.wait_settled(timeout_s=1)
    assert info.value.code == "0F"
    assert "Following error" in info.value.meaning
    t.assert_done()


def test_unterminated_reply_times_out_and_the_rest_is_discarded_before_the_next_command():
    t, mirror = scripted([(b"1TP\r\n", b"1TP12.5"), (b"1TS\r\n", b"1TS000033\r\n")])
    with pytest.raises(DeviceTimeout):
        mirror.position()
    t.feed(b"\r\n")   # the end of the late reply arrives
    assert mirror.state() == "ready"
    assert t.drained == [b"1TP12.5\r\n"]
    t.assert_done()


def test_a_reply_to_an_earlier_exchange_is_passed_over_for_this_ones():
    # a TE reply sent twice (its exchange repeated after the link broke) or arriving past its
    # timeout comes before the TS reply: the TS query reads on to its own reply, and the next
    # exchange is not shifted by one
    t, mirror = scripted([(b"1TS\r\n", b"1TE@\r\n1TS000033\r\n"), (b"1TP\r\n", b"1TP12.5\r\n")])
    assert mirror.state() == "ready"
    assert mirror.position() == pytest.approx(12.5)
    t.assert_done()


@pytest.mark.parametrize("reply", [
    b"1TS12.5\r\n",          # answer to another command
    b"2TP12.5\r\n",          # another controller address
    b"1TPabc\r\n",           # not a number
    b"1TP\xff\xfe\r\n",      # not ASCII
    b"1TP12.5\n",            # LF without CR
])
def test_malformed_replies_raise_protocol_error_with_raw_bytes(reply):
    t, mirror = scripted([(b"1TP\r\n", reply)])
    with pytest.raises(ProtocolError) as info:
        mirror.position()
    assert info.value.raw == reply
    t.assert_done()


def test_malformed_ts_and_te():
    t, mirror = scripted([(b"1TS\r\n", b"1TS0000ZZ\r\n"), (b"1TE\r\n", b"1TE?\r\n")])
    with pytest.raises(ProtocolError):
        mirror.state()
    with pytest.raises(ProtocolError):
        mirror.last_error()
    t.assert_done()


def test_a_dropped_link_is_reopened_once_and_the_exchange_repeated():
    t, mirror = scripted([(b"1TP\r\n", OSError(5, "Input/output error")), (b"1TP\r\n", b"1TP1.5\r\n")])
    assert mirror.position() == 1.5
    assert t.reconnects == 1
    t2, mirror2 = scripted([(b"1TP\r\n", OSError(5, "EIO")), (b"1TP\r\n", OSError(5, "EIO"))])
    with pytest.raises(ConnectionLost):
        mirror2.position()


def test_context_manager_stops_motion_even_when_the_body_raises():
    t, mirror = scripted([(b"1ST\r\n", None)])
    with pytest.raises(RuntimeError):
        with mirror:
            raise RuntimeError("body failed")
    t.assert_done()
    with pytest.raises(ConnectionLost):
        mirror.position()


def test_bad_arguments_are_rejected_with_clear_errors():
    with pytest.raises(ValueError, match="address"):
        SMC100Mirror("loop://", address=0)
    with pytest.raises(ValueError, match="serial port"):
        SMC100Mirror()
    with pytest.raises(ValueError, match="xonxoff"):
        SMC100Mirror("loop://", xonxoff="yes")
    t, mirror = scripted([])
    with pytest.raises(ValueError, match="finite"):
        mirror.move_to(float("nan"))
    with pytest.raises(ValueError, match="timeout_s"):
        mirror.wait_settled(timeout_s=0)
    t.assert_done()


def test_value_formatting_and_error_bits():
    assert [format_value(v) for v in (12.5, -3.0, 0.0, -0.0, 1e-7, 0.1234567)] == \
        ["12.5", "-3", "0", "0", "0", "0.123457"]
    assert decode_positioner_errors(0x0003) == ["Positive end of run", "Negative end of run"]
    assert decode_positioner_errors(0) == []


# ---------------------------------------------------------------- integration: the serial transport
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


def test_serial_settings_are_57600_8n1_with_xonxoff_by_default():
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        path = os.ttyname(slave)
        with SMC100Mirror(path) as mirror:
            ser = mirror.transport.serial
            assert (ser.baudrate, ser.bytesize, ser.parity, ser.stopbits) == (57600, 8, "N", 1)
            assert ser.xonxoff and not ser.rtscts
            assert termios.tcgetattr(ser.fd)[0] & termios.IXON
            os.write(master, b"1TP2.5\r\n")   # answered before it is asked: read as the reply
            assert mirror.position() == 2.5
            assert os.read(master, 64) == b"1TP\r\n"
        with SMC100Mirror(path, xonxoff=False) as mirror:
            assert not mirror.transport.serial.xonxoff
    finally:
        os.close(master)
        os.close(slave)
