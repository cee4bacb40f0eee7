"""Exact USBTMC frames and control requests the laser-sync driver puts on the bus.

The simulated device records every transfer (``backend.log``); these tests
assert the bytes of each Bulk-OUT frame and each class request against
USBTMC 1.0 (header layout, bTag sequence, padding, abort and clear sequences).
"""
from __future__ import annotations

import struct

import pytest

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.interfaces import LaserSync
from drivers.scpi_sync import ScpiLaserSync, format_number
from drivers.sim.usbtmc import UsbtmcBackend
from drivers.usbtmc import UsbtmcTransport, dev_dep_msg_out, request_dev_dep_msg_in

pytestmark = pytest.mark.timeout(20)

VID, PID = 0x1209, 0x5A17
READ_SIZE = 65536


def msg_out(tag, payload, eom=True):
    """DEV_DEP_MSG_OUT written out field by field from USBTMC 1.0 tables 1 and 3."""
    size = len(payload)
    header = bytes([1, tag, 0xFF - tag, 0x00]) + size.to_bytes(4, "little") + \
        bytes([0x01 if eom else 0x00, 0x00, 0x00, 0x00])
    return header + payload + b"\x00" * ((4 - size % 4) % 4)


def req_in(tag, size=READ_SIZE):
    """REQUEST_DEV_DEP_MSG_IN from USBTMC 1.0 tables 1 and 4 (no TermChar)."""
    return bytes([2, tag, 0xFF - tag, 0x00]) + size.to_bytes(4, "little") + bytes(4)


def bulk_out(log):
    return [entry[2] for entry in log if entry[0] == "bulk_out"]


def controls(log):
    return [entry[1:] for entry in log if entry[0] == "ctrl"]


@pytest.fixture
def device():
    backend = UsbtmcBackend()
    sync = ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.3)
    yield backend, sync
    sync.close()


def test_driver_implements_the_laser_sync_interface(device):
    assert isinstance(device[1], LaserSync)


def test_open_asks_for_capabilities_and_nothing_else(device):
    backend, sync = device
    assert controls(backend.log) == [(0xA1, 7, 0x0000, 0, 0x18)]   # GET_CAPABILITIES
    caps = sync.transport.capabilities
    assert caps.bcd_usbtmc == 0x0100 and caps.bcd_usb488 == 0x0100 and caps.term_char


def test_header_helpers_match_the_spec_layout():
    assert dev_dep_msg_out(0x5B, b"*RST\n") == msg_out(0x5B, b"*RST\n")
    assert dev_dep_msg_out(0x5B, b"*RST\n")[:4] == b"\x01\x5b\xa4\x00"   # the spec's bTagInverse example
    assert request_dev_dep_msg_in(7, 100) == req_in(7, 100)
    assert request_dev_dep_msg_in(7, 100, term_char=0x0A) == \
        bytes([2, 7, 0xF8, 0, 100, 0, 0, 0, 0x02, 0x0A, 0, 0])
    for n in range(1, 10):
        frame = dev_dep_msg_out(1, b"x" * n)
        assert len(frame) % 4 == 0 and len(frame) == 12 + n + (-n) % 4
        assert frame[12 + n:] == b"\x00" * ((-n) % 4)
    with pytest.raises(ValueError):
        dev_dep_msg_out(0, b"x")
    with pytest.raises(ValueError):
        dev_dep_msg_out(1, b"")


def test_identify_is_one_message_and_one_request_with_consecutive_tags(device):
    backend, sync = device
    backend.clear_log()
    assert sync.identify() == "STREAKLAB,SLS-575SIM,SLS0001,1.0"
    assert bulk_out(backend.log) == [msg_out(1, b"*IDN?\n"), req_in(2)]
    reply = b"".join(e[2] for e in backend.log if e[0] == "bulk_in")
    assert reply[:12] == bytes([2, 2, 0xFD, 0]) + (33).to_bytes(4, "little") + bytes([1, 0, 0, 0])
    assert reply[12:] == b"STREAKLAB,SLS-575SIM,SLS0001,1.0\n" + b"\x00" * 3


@pytest.mark.parametrize("call, wire", [
    (lambda s: s.set_repetition_rate(80e6), b":PULS0:PER 1.25e-08\n"),
    (lambda s: s.set_trigger_delay(1234.5), b":PULS1:DEL 1.2345e-09\n"),
    (lambda s: s.set_trigger_delay(500.0, channel=3), b":PULS3:DEL 5e-10\n"),
    (lambda s: s.set_output(True), b":PULS0:STAT ON\n"),
    (lambda s: s.set_output(False), b":PULS0:STAT OFF\n"),
])
def test_setting_commands_are_followed_by_an_error_queue_read(device, call, wire):
    backend, sync = device
    backend.clear_log()
    call(sync)
    assert bulk_out(backend.log) == [msg_out(1, wire), msg_out(2, b"SYST:ERR?\n"), req_in(3)]


def test_read_errors_drains_the_queue(device):
    backend, sync = device
    backend.instrument.push_error(-113)
    backend.instrument.push_error(-222)
    backend.clear_log()
    assert sync.read_errors() == [(-113, "Undefined header"), (-222, "Data out of range")]
    assert bulk_out(backend.log) == [msg_out(1, b"SYST:ERR?\n"), req_in(2), msg_out(3, b"SYST:ERR?\n"),
                                     req_in(4), msg_out(5, b"SYST:ERR?\n"), req_in(6)]
    assert sync.read_errors() == []


def test_btag_wraps_from_255_to_1_never_0(device):
    backend, sync = device
    sync.transport._tag = 253
    backend.clear_log()
    sync.identify()
    sync.identify()
    tags = [frame[1] for frame in bulk_out(backend.log)]
    assert tags == [254, 255, 1, 2]
    assert all(frame[2] == 0xFF - frame[1] for frame in bulk_out(backend.log))


def test_device_error_carries_the_scpi_code_and_text(device):
    backend, sync = device
    with pytest.raises(DeviceError) as info:
        sync.set_trigger_delay(-10.0)
    assert info.value.code == -222
    assert info.value.meaning == "Data out of range"
    assert info.value.command == ":PULS1:DEL -1e-11"


def test_timeout_runs_the_abort_bulk_in_sequence_then_the_next_query_works(device):
    backend, sync = device
    backend.inject("drop_reply", "*IDN?")
    backend.clear_log()
    with pytest.raises(DeviceTimeout):
        sync.identify()
    # request tag 2 timed out: INITIATE_ABORT_BULK_IN(bTag 2) on EP 0x81, read the short
    # packet, CHECK_ABORT_BULK_IN_STATUS until not pending
    assert controls(backend.log) == [(0xA2, 3, 2, 0x81, 2), (0xA2, 4, 0, 0x81, 8)]
    assert ("bulk_in", 0x81, b"") in backend.log
    assert sync.identify().startswith("STREAKLAB")


class WrongTagBackend(UsbtmcBackend):
    """Answers the next request with a header whose bTag is one off."""

    corrupt = False

    def _fulfil(self):
        before = len(self._in_fifo)
        super()._fulfil()
        if self.corrupt and len(self._in_fifo) > before:
            data = bytearray(self._in_fifo[-1][0])
            data[1] = (data[1] % 255) + 1
            data[2] = ~data[1] & 0xFF
            self._in_fifo[-1][0] = bytes(data)
            self.corrupt = False


def test_reply_with_another_btag_is_a_protocol_error_and_the_driver_clears():
    backend = WrongTagBackend()
    with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.3) as sync:
        backend.corrupt = True
        backend.clear_log()
        with pytest.raises(ProtocolError, match="bTag 3 does not match request 2") as info:
            sync.identify()
        assert info.value.raw[:4] == bytes([2, 3, 0xFC, 0])
        # INITIATE_CLEAR, CHECK_CLEAR_STATUS, CLEAR_FEATURE(ENDPOINT_HALT) on Bulk-OUT 0x02
        assert controls(backend.log) == [(0xA1, 5, 0, 0, 1), (0xA1, 6, 0, 0, 2), (0x02, 1, 0, 0x02, 0)]
        assert sync.identify().startswith("STREAKLAB")


def test_bulk_out_abort_sequence():
    backend = UsbtmcBackend()
    transport = UsbtmcTransport(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.3)
    dev = transport._dev
    # a transfer announcing 100 bytes of which only 8 arrive: the device waits for the rest
    dev.write(0x02, bytes([1, 9, 0xF6, 0]) + (100).to_bytes(4, "little") + bytes([1, 0, 0, 0]) + b"*IDN?;*O")
    backend.clear_log()
    transport._abort_bulk_out(9)
    assert controls(backend.log) == [(0xA2, 1, 9, 0x02, 2), (0xA2, 2, 0, 0x02, 8), (0x02, 1, 0, 0x02, 0)]
    assert transport.query(b"*IDN?\n").startswith(b"STREAKLAB")
    transport.close()


def test_clear_sequence(device):
    backend, sync = device
    backend.clear_log()
    sync.transport.clear()
    assert controls(backend.log) == [(0xA1, 5, 0, 0, 1), (0xA1, 6, 0, 0, 2), (0x02, 1, 0, 0x02, 0)]


def test_messages_longer_than_one_transfer_are_split_with_eom_on_the_last(device):
    backend, sync = device
    backend.clear_log()
    sync.transport._write(b"*CLS;" * 5 + b"*OPC?\n", chunk=10)
    frames = bulk_out(backend.log)
    assert [f[8] for f in frames] == [0, 0, 0, 1]
    assert [struct.unpack("<I", f[4:8])[0] for f in frames] == [10, 10, 10, 1]
    assert sync.transport.read() == b"1\n"


def test_response_longer_than_the_requested_size_comes_in_several_transfers():
    backend = UsbtmcBackend()
    transport = UsbtmcTransport(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.3,
                                max_read_size=8)
    backend.clear_log()
    assert transport.query(b"*IDN?\n") == b"STREAKLAB,SLS-575SIM,SLS0001,1.0\n"
    requests = [f for f in bulk_out(backend.log) if f[0] == 2]
    assert len(requests) == 5 and all(struct.unpack("<I", f[4:8])[0] == 8 for f in requests)
    transport.close()


def test_context_exit_disables_the_output_even_when_the_body_raises():
    backend = UsbtmcBackend()
    with pytest.raises(RuntimeError):
        with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.3) as sync:
            sync.set_output(True)
            assert backend.lab_state.sync_output_enabled
            backend.clear_log()
            raise RuntimeError("capture failed")
    assert bulk_out(backend.log)[0] == msg_out(sync.transport._tag - 2, b":PULS0:STAT OFF\n")
    assert backend.lab_state.sync_output_enabled is False
    with pytest.raises(ConnectionLost):
        sync.identify()


def test_bad_arguments_are_rejected_before_anything_is_sent(device):
    backend, sync = device
    backend.clear_log()
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="rate_hz"):
            sync.set_repetition_rate(bad)
    with pytest.raises(ValueError, match="delay_ps"):
        sync.set_trigger_delay(float("nan"))
    with pytest.raises(ValueError, match="channel"):
        sync.set_trigger_delay(10.0, channel=0)
    with pytest.raises(ValueError, match="timeout_s"):
        UsbtmcTransport(backend=backend, timeout_s=0)
    assert list(backend.log) == []
    assert format_number(1 / 80e6) == "1.25e-08"


def test_device_not_found_names_what_was_looked_for():
    with pytest.raises(ConnectionLost, match="idVendor=0x1234 idProduct=0x0001.*not found"):
        UsbtmcTransport(vendor_id=0x1234, product_id=0x0001, backend=UsbtmcBackend())


def test_found_by_serial_number_read_from_the_string_descriptor():
    backend = UsbtmcBackend(serial_number="SLS0042")
    with pytest.raises(ConnectionLost, match="serial='SLS0001'"):
        UsbtmcTransport(serial_number="SLS0001", backend=backend)
    transport = UsbtmcTransport(serial_number="SLS0042", backend=backend)
    # GET_DESCRIPTOR(STRING 0) for the LANGIDs, then STRING 3 in US English
    assert (0x80, 6, 0x0300, 0, 254) in controls(backend.log)
    assert (0x80, 6, 0x0303, 0x0409, 254) in controls(backend.log)
    transport.close()
