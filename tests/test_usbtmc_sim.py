"""The laser-sync driver against the simulated USBTMC device through pyusb; device conformance."""
from __future__ import annotations

import errno
import struct
import threading
import time

import pytest
import usb.core
import usb.util

from drivers.errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError
from drivers.scpi_sync import ScpiLaserSync
from drivers.sim.state import LabState
from drivers.sim.usbtmc import UsbtmcBackend

pytestmark = pytest.mark.timeout(30)

VID, PID = 0x1209, 0x5A17


@pytest.fixture
def lab():
    state = LabState()
    backend = UsbtmcBackend(state)
    with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, timeout_s=0.5) as sync:
        yield backend, sync, state


# ---------------------------------------------------------------- the instrument through the driver
def test_settings_reach_the_lab_state_and_read_back(lab):
    backend, sync, state = lab
    sync.set_repetition_rate(76e6)
    sync.set_trigger_delay(3456.7)
    sync.set_trigger_delay(99.0, channel=2)
    sync.set_output(True)
    assert state.sync_rate_hz == pytest.approx(76e6, rel=1e-12)
    assert state.sync_delay_ps == 3456.7       # channel 1 (the camera trigger); 0.1 ps resolution
    assert state.sync_output_enabled is True
    assert sync.repetition_rate() == pytest.approx(76e6, rel=1e-12)
    assert sync.trigger_delay() == 3456.7
    assert sync.trigger_delay(channel=2) == 99.0
    assert sync.output_enabled() is True
    sync.reset()
    assert (state.sync_rate_hz, state.sync_delay_ps, state.sync_output_enabled) == (80e6, 0.0, False)


def test_camera_sees_light_only_with_system_output_and_its_channel_on():
    state = LabState()
    backend = UsbtmcBackend(state, camera_channel=2)
    with ScpiLaserSync(vendor_id=VID, product_id=PID, backend=backend, camera_channel=2) as sync:
        sync.set_trigger_delay(10.0, channel=1)
        sync.set_trigger_delay(250.0)                  # the driver's camera channel: 2
        assert state.sync_delay_ps == 250.0
        sync.set_output(True)
        assert state.sync_output_enabled is True
        sync.write(":PULS2:STAT OFF")
        assert state.sync_output_enabled is False
        sync.write(":PULS2:STAT ON")
        assert state.sync_output_enabled is True
    assert state.sync_output_enabled is False          # leaving the block switched the output off


def test_delay_is_quantised_to_the_device_resolution(lab):
    backend, sync, state = lab
    sync.set_trigger_delay(1000.04)
    assert sync.trigger_delay() == 1000.0
    assert state.sync_delay_ps == 1000.0


def test_scpi_long_forms_compound_messages_and_errors(lab):
    backend, sync, state = lab
    sync.write(":PULSe1:DELay 2e-9;:PULSE0:STATE ON")
    assert state.sync_delay_ps == 2000.0 and state.sync_output_enabled
    assert sync.query("*OPC?;:PULS0:STAT?") == "1;1"
    sync.write(":PULS9:DEL 1e-9")           # no channel 9
    sync.write(":PULS1:DEL")                # missing parameter
    sync.write(":PULS0:STAT MAYBE")         # illegal value
    sync.write(":PULS0:PER abc")            # not a number
    assert sync.read_errors() == [(-113, "Undefined header"), (-109, "Missing parameter"),
                                  (-224, "Illegal parameter value"), (-104, "Data type error")]


def test_unread_response_is_interrupted_by_the_next_message(lab):
    backend, sync, state = lab
    sync.write("*IDN?")
    assert sync.query("*OPC?") == "1"
    assert sync.read_errors() == [(-410, "Query INTERRUPTED")]


def test_rate_out_of_range_is_a_device_error_and_changes_nothing(lab):
    backend, sync, state = lab
    with pytest.raises(DeviceError) as info:
        sync.set_repetition_rate(1e9)      # 1 ns period: below the 5 ns minimum
    assert info.value.code == -222
    assert state.sync_rate_hz == 80e6


# ---------------------------------------------------------------- faults
def test_drop_reply_times_out_within_the_timeout_then_works(lab):
    backend, sync, state = lab
    backend.inject("drop_reply", "*IDN?")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        sync.identify()
    assert time.monotonic() - t0 < 1.5
    assert sync.identify().startswith("STREAKLAB")


def test_delayed_reply_is_aborted_and_never_read_as_a_later_answer(lab):
    backend, sync, state = lab
    sync.set_repetition_rate(50e6)
    backend.inject("delay", "*IDN?", delay_s=1.0)     # twice the driver's 0.5 s timeout
    with pytest.raises(DeviceTimeout):
        sync.identify()
    time.sleep(0.8)  # past the moment the late reply would have been ready
    assert sync.repetition_rate() == pytest.approx(50e6)
    assert sync.identify().startswith("STREAKLAB")


def test_garbage_is_a_protocol_error_then_works(lab):
    backend, sync, state = lab
    backend.inject("garbage", "*IDN?")
    with pytest.raises(ProtocolError) as info:
        sync.identify()
    assert info.value.raw[:4] == bytes([0x7F, 0x00, 0x13, 0x37])
    assert sync.identify().startswith("STREAKLAB")


def test_injected_device_error_is_raised_with_its_meaning(lab):
    backend, sync, state = lab
    backend.inject("error", ":PULS0:PER", code=-240)
    with pytest.raises(DeviceError) as info:
        sync.set_repetition_rate(40e6)
    assert (info.value.code, info.value.meaning) == (-240, "Hardware error")
    assert state.sync_rate_hz == 80e6
    sync.set_repetition_rate(40e6)
    assert state.sync_rate_hz == pytest.approx(40e6)


def test_replug_is_survived_by_one_reconnect(lab):
    backend, sync, state = lab
    sync.set_output(True)
    old_address = backend.enumerate_devices()[0].address
    backend.inject("close", "*IDN?")
    assert sync.identify().startswith("STREAKLAB")
    assert backend.enumerate_devices()[0].address != old_address
    assert sync.output_enabled() is True   # instrument settings survive a USB re-plug


def test_unplug_is_connection_lost_within_the_timeout(lab):
    backend, sync, state = lab
    backend.inject("unplug")
    t0 = time.monotonic()
    with pytest.raises(ConnectionLost):
        sync.identify()
    assert time.monotonic() - t0 < 1.5
    with pytest.raises(ConnectionLost):
        sync.set_output(False)


def test_a_halted_bulk_in_endpoint_is_a_protocol_error_and_is_cleared(lab):
    backend, sync, state = lab
    sync.transport._dev.ctrl_transfer(0x02, 3, 0, 0x81, None)   # SET_FEATURE(ENDPOINT_HALT) on Bulk-IN
    with pytest.raises(ProtocolError, match="Pipe error"):
        sync.identify()
    assert sync.identify().startswith("STREAKLAB")


# ---------------------------------------------------------------- threads
def test_two_threads_sharing_one_driver_get_their_own_replies(lab):
    backend, sync, state = lab
    sync.set_repetition_rate(40e6)
    sync.set_trigger_delay(777.7)
    errors = []

    def worker(fn, expected, n=80):
        try:
            for _ in range(n):
                got = fn()
                if got != expected:
                    errors.append((fn.__name__, got))
        except Exception as exc:  # recorded, asserted below
            errors.append(exc)

    idn = sync.identify()
    threads = [threading.Thread(target=worker, args=(sync.identify, idn)),
               threading.Thread(target=worker, args=(sync.repetition_rate, 40e6)),
               threading.Thread(target=worker, args=(sync.trigger_delay, 777.7)),
               threading.Thread(target=worker, args=(sync.read_errors, []))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert not any(t.is_alive() for t in threads)
    assert errors == []


# ---------------------------------------------------------------- conformance, with plain pyusb
def _raw_device(backend):
    def is_usbtmc(dev):
        return any(i.bInterfaceClass == 0xFE and i.bInterfaceSubClass == 0x03 for c in dev for i in c)
    dev = usb.core.find(backend=backend, custom_match=is_usbtmc)
    assert dev is not None
    return dev


def test_standard_descriptors_are_consistent_and_well_formed():
    backend = UsbtmcBackend()
    dev = _raw_device(backend)
    raw = bytes(usb.control.get_descriptor(dev, 18, usb.util.DESC_TYPE_DEVICE, 0))
    fields = struct.unpack("<BBHBBBBHHHBBBB", raw)
    assert fields == (18, 1, 0x0200, 0, 0, 0, 64, VID, PID, 0x0100, 1, 2, 3, 1)
    cfg = dev.get_active_configuration()
    total = bytes(usb.control.get_descriptor(dev, 255, usb.util.DESC_TYPE_CONFIG, 0))
    assert len(total) == cfg.wTotalLength == 9 + 9 + 3 * 7
    intf = cfg[(0, 0)]
    assert total[9:18] == bytes([9, 4, 0, 0, 3, 0xFE, 0x03, 0x01, 0])
    eps = {e.bEndpointAddress: e for e in intf}
    assert set(eps) == {0x02, 0x81, 0x83}
    assert usb.util.endpoint_type(eps[0x02].bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
    assert usb.util.endpoint_type(eps[0x83].bmAttributes) == usb.util.ENDPOINT_TYPE_INTR
    # every descriptor chained in the configuration bundle: bLength, bDescriptorType
    pos, kinds = 0, []
    while pos < len(total):
        kinds.append(total[pos + 1])
        pos += total[pos]
    assert kinds == [2, 4, 5, 5, 5] and pos == len(total)
    assert (dev.manufacturer, dev.product, dev.serial_number) == \
        ("Streaklab", "Laser sync SLS-575 (simulated)", "SLS0001")
    usb.util.dispose_resources(dev)


def test_a_plain_pyusb_client_can_talk_to_it_with_termchar_and_status_byte():
    backend = UsbtmcBackend()
    dev = _raw_device(backend)
    usb.util.claim_interface(dev, 0)
    caps = dev.ctrl_transfer(0xA1, 7, 0, 0, 0x18)
    assert caps[0] == 1 and caps[5] & 0x01               # TermChar supported
    dev.write(0x02, bytes([1, 1, 0xFE, 0, 12, 0, 0, 0, 1, 0, 0, 0]) + b"*IDN?;*OPC?\n")
    # READ_STATUS_BYTE: the status byte (MAV set) arrives on interrupt-IN
    assert list(dev.ctrl_transfer(0xA1, 128, 5, 0, 3)) == [1, 5, 0]
    note = dev.read(0x83, 2, 500)
    assert note[0] == 0x80 | 5 and note[1] & 0x10
    # TermChar ',' : the transfer stops after the first comma, without EOM
    dev.write(0x02, bytes([2, 2, 0xFD, 0, 64, 0, 0, 0, 0x02, ord(","), 0, 0]))
    data = bytes(dev.read(0x81, 512, 500))
    assert data[:4] == bytes([2, 2, 0xFD, 0]) and data[8] == 0x02
    size = struct.unpack("<I", data[4:8])[0]
    assert data[12:12 + size] == b"STREAKLAB,"
    dev.write(0x02, bytes([2, 3, 0xFC, 0, 255, 0, 0, 0, 0, 0, 0, 0]))
    data = bytes(dev.read(0x81, 512, 500))
    size = struct.unpack("<I", data[4:8])[0]
    assert data[8] == 0x01 and data[12:12 + size] == b"SLS-575SIM,SLS0001,1.0;1\n"
    usb.util.dispose_resources(dev)


def test_bad_header_stalls_bulk_out_until_clear_feature():
    backend = UsbtmcBackend()
    dev = _raw_device(backend)
    with pytest.raises(usb.core.USBError) as info:
        dev.write(0x02, bytes([1, 7, 0x00, 0, 4, 0, 0, 0, 1, 0, 0, 0]) + b"*RST")  # bTagInverse wrong
    assert info.value.errno == errno.EPIPE
    assert list(dev.ctrl_transfer(0x82, 0, 0, 0x02, 2)) == [1, 0]     # GET_STATUS: halted
    with pytest.raises(usb.core.USBError):
        dev.write(0x02, bytes([1, 8, 0xF7, 0, 4, 0, 0, 0, 1, 0, 0, 0]) + b"*RST")
    dev.clear_halt(0x02)
    assert list(dev.ctrl_transfer(0x82, 0, 0, 0x02, 2)) == [0, 0]
    dev.write(0x02, bytes([1, 9, 0xF6, 0, 4, 0, 0, 0, 1, 0, 0, 0]) + b"*RST")
    usb.util.dispose_resources(dev)


def test_unknown_requests_stall_and_reads_time_out_like_libusb():
    backend = UsbtmcBackend()
    dev = _raw_device(backend)
    with pytest.raises(usb.core.USBError) as info:
        dev.ctrl_transfer(0xA1, 99, 0, 0, 1)                 # no such class request
    assert info.value.errno == errno.EPIPE
    with pytest.raises(usb.core.USBError):
        dev.ctrl_transfer(0xA1, 7, 0, 0, 4)                  # GET_CAPABILITIES with wrong wLength
    t0 = time.monotonic()
    with pytest.raises(usb.core.USBTimeoutError) as info:
        dev.read(0x81, 64, 200)                              # nothing was requested
    elapsed = time.monotonic() - t0
    assert info.value.errno == errno.ETIMEDOUT and info.value.backend_error_code == -7
    assert 0.15 <= elapsed < 2.0
    usb.util.dispose_resources(dev)


def test_interface_claims_are_exclusive_between_handles():
    backend = UsbtmcBackend()
    first, second = _raw_device(backend), _raw_device(backend)
    usb.util.claim_interface(first, 0)
    with pytest.raises(usb.core.USBError) as info:
        usb.util.claim_interface(second, 0)
    assert info.value.errno == errno.EBUSY
    usb.util.dispose_resources(first)
    usb.util.claim_interface(second, 0)
    usb.util.dispose_resources(second)


def test_closing_the_simulator_wakes_a_blocked_read_with_no_device():
    backend = UsbtmcBackend()
    dev = _raw_device(backend)
    usb.util.claim_interface(dev, 0)
    outcome = []

    def reader():
        try:
            dev.read(0x81, 64, 10000)
        except usb.core.USBError as exc:
            outcome.append(exc.errno)

    thread = threading.Thread(target=reader)
    thread.start()
    time.sleep(0.1)
    t0 = time.monotonic()
    backend.close()
    thread.join(5)
    assert not thread.is_alive() and time.monotonic() - t0 < 2.0
    assert outcome == [errno.ENODEV]
    assert backend.enumerate_devices() == []
