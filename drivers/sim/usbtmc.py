"""Simulated laser sync unit: a pyusb backend that *is* a USBTMC/USB488 delay generator.

:class:`UsbtmcBackend` subclasses :class:`usb.backend.IBackend`, so
``usb.core.find(backend=sim)`` enumerates one full-speed USB device and every
pyusb call (descriptors, configuration, claiming, bulk, interrupt and control
transfers) reaches the simulated device instead of libusb.  The device follows
the USB Test and Measurement Class specification, USBTMC 1.0 (USB-IF, 2003)
and its USB488 subclass specification:

* descriptors: device (class 0 at device level), one configuration, one
  interface of class 0xFE / subclass 0x03 / protocol 0x01 (USB488) with a
  bulk-OUT, a bulk-IN and an interrupt-IN endpoint; string descriptors for
  manufacturer, product and serial number (USB 2.0 spec, chapter 9);
* Bulk-OUT: 12-byte headers (USBTMC 1.0 tables 1-4), DEV_DEP_MSG_OUT (1)
  carries message bytes with EOM, REQUEST_DEV_DEP_MSG_IN (2) asks for a
  response of at most TransferSize bytes, optionally ending at a TermChar;
  alignment bytes pad every transfer to a multiple of 4.  A header whose
  bTagInverse does not match, whose reserved byte is not 0, or whose MsgID is
  unsupported halts the Bulk-OUT endpoint (STALL) until CLEAR_FEATURE;
* Bulk-IN: DEV_DEP_MSG_IN (2) transfers answer the armed request, echoing
  its bTag (tables 9-11);
* class requests (table 15): INITIATE/CHECK_ABORT_BULK_OUT (1/2),
  INITIATE/CHECK_ABORT_BULK_IN (3/4), INITIATE_CLEAR/CHECK_CLEAR_STATUS
  (5/6), GET_CAPABILITIES (7), USB488 READ_STATUS_BYTE (128, the status byte
  then arrives on interrupt-IN); status values per table 16;
* standard requests: GET_DESCRIPTOR, GET_STATUS, CLEAR/SET_FEATURE
  (ENDPOINT_HALT), GET/SET_CONFIGURATION, GET/SET_INTERFACE; anything else
  STALLs.  Errors are raised as pyusb raises libusb's: ``USBError`` with
  libusb's error code and errno, ``USBTimeoutError`` after the requested
  timeout when no data comes.

The instrument behind the interface speaks SCPI (IEEE 488.2 common commands
plus a pulse/delay-generator tree in the style of BNC 575-type units); see
:data:`COMMANDS_DOC` and ``docs/laser-sync.md``.  It writes the shared
:class:`~drivers.sim.state.LabState`: ``sync_rate_hz`` (1 / system period),
``sync_delay_ps`` (delay of the camera channel, 1 by default) and
``sync_output_enabled`` (system output and camera channel both on).

Layout: the SCPI instrument is :mod:`drivers.sim.scpi_instrument`; USB
constants, descriptors and enumeration are :mod:`drivers.sim.usb_device`; this
module is the device's transfer state machine (Bulk-OUT parsing, Bulk-IN
responses, class and standard requests, faults).  It stays one module of
about 560 lines because that state (armed request, pending response, abort
and halt flags) is shared by every transfer and request handler under one
condition variable; splitting it would spread one lock's invariants over
several files.

Fault injection (one-shot, :mod:`drivers.sim.faults`; ``command`` is the SCPI
header as sent, without a leading colon, case-insensitive, e.g. ``"*IDN?"``)::

    sim.inject("drop_reply", "*IDN?")      # executed; the response never comes (host times out)
    sim.inject("delay", "*IDN?", delay_s=1) # the response comes after 1 s
    sim.inject("garbage")                   # the next response transfer is not USBTMC
    sim.inject("error", "PULS0:PER", code=-222)  # not executed; error queued for SYST:ERR?
    sim.inject("close")                     # device unplugged and re-plugged: open handles die
    sim.inject("unplug")                    # device unplugged for good
"""
from __future__ import annotations

import array
import collections
import struct
import threading
import time

import usb.backend

from .faults import COMMON_KINDS, FaultInjector
from .scpi_instrument import COMMANDS_DOC, SCPI_ERRORS, SyncInstrument  # noqa: F401 (re-exported)
from .state import LabState
from .usb_device import (CHECK_ABORT_BULK_IN_STATUS, CHECK_ABORT_BULK_OUT_STATUS, CHECK_CLEAR_STATUS,
                         CONFIG_VALUE, DEV_DEP_MSG_IN, DEV_DEP_MSG_OUT, EP_BULK_IN, EP_BULK_OUT, EP_INTR_IN,
                         GET_CAPABILITIES, INITIATE_ABORT_BULK_IN, INITIATE_ABORT_BULK_OUT, INITIATE_CLEAR,
                         INTERFACE_NUMBER, READ_STATUS_BYTE, REQUEST_DEV_DEP_MSG_IN, STATUS_FAILED,
                         STATUS_PENDING, STATUS_SUCCESS, STATUS_TRANSFER_NOT_IN_PROGRESS, UsbDescriptors,
                         _DeviceId, _Handle, _usb_error)

_GARBAGE = bytes([0x7F, 0x00, 0x13, 0x37]) + b"\xde\xad\xbe\xef" * 3


class UsbtmcBackend(UsbDescriptors, usb.backend.IBackend):
    """A pyusb backend with one simulated USBTMC/USB488 laser sync unit attached.

    Parameters
    ----------
    lab_state : LabState, optional
        Shared virtual-lab state (a private one if omitted).
    vendor_id, product_id : int
        USB ids the device enumerates with.
    serial_number : str
        iSerialNumber string (also in ``*IDN?``).
    manufacturer, product : str
        iManufacturer / iProduct strings.
    log_length : int
        How many transfers :attr:`log` keeps.
    camera_channel : int
        Delay channel wired to the streak camera's trigger (see :class:`SyncInstrument`).
    reference_noise_ps : float
        RMS noise of the unit's trigger-interval measurements, ps (see :class:`SyncInstrument`).

    Attributes
    ----------
    log : collections.deque of tuple
        The last ``log_length`` transfers, in order: ``("ctrl", bmRequestType, bRequest, wValue,
        wIndex, payload_or_length)``, ``("bulk_out", ep, bytes)``,
        ``("bulk_in", ep, bytes)``, ``("intr_in", ep, bytes)``.
    instrument : SyncInstrument
        The SCPI instrument state.
    """

    def __init__(self, lab_state: LabState | None = None, *, vendor_id: int = 0x1209,
                 product_id: int = 0x5A17, serial_number: str = "SLS0001",
                 manufacturer: str = "Streaklab", product: str = "Laser sync SLS-575 (simulated)",
                 log_length: int = 10000, camera_channel: int = 1, reference_noise_ps: float = 0.5):
        super().__init__()
        self.lab_state = lab_state if lab_state is not None else LabState()
        self.vendor_id, self.product_id = int(vendor_id), int(product_id)
        self.serial_number = serial_number
        self.strings = {1: manufacturer, 2: product, 3: serial_number}
        self.instrument = SyncInstrument(self.lab_state, serial_number, camera_channel=camera_channel,
                                         reference_noise_ps=reference_noise_ps)
        self.faults = FaultInjector(COMMON_KINDS | {"unplug"})
        self.log: collections.deque = collections.deque(maxlen=int(log_length))
        self._cv = threading.Condition(threading.RLock())
        self._generation = 0
        self._address = 5
        self._plugged = True
        self._dev = _DeviceId(1, self._address, self._generation)
        self._configuration = CONFIG_VALUE   # the host's enumeration has configured it
        self._claims: dict[int, _Handle] = {}
        self._reset_transfer_state()

    # ------------------------------------------------------------ test controls
    def inject(self, kind: str, command: str | None = None, **kwargs) -> None:
        """Arm a one-shot fault (see the module docstring and :class:`FaultInjector`).

        ``command`` is an SCPI header as sent (``"*IDN?"``, ``"PULS0:PER"``); a
        leading colon is ignored.  None matches the next message of any kind.
        """
        if command is not None:
            command = command.lstrip(":")
        self.faults.inject(kind, command, **kwargs)

    def close(self) -> None:
        """Unplug the device for good: open handles fail with ENODEV, blocked reads return."""
        self._unplug(replug=False)

    def clear_log(self) -> None:
        with self._cv:
            self.log.clear()

    def _reset_transfer_state(self) -> None:
        self._halted: set[int] = set()
        self._out_hdr = None          # (msgid, tag, size, attrs) of a Bulk-OUT transfer in progress
        self._out_got = 0
        self._out_pad = 0
        self._out_tag = 0             # bTag of the last Bulk-OUT header
        self._msg = bytearray()       # DEV_DEP_MSG_OUT bytes of the message being received
        self._output = bytearray()    # responses waiting for REQUEST_DEV_DEP_MSG_IN
        self._output_fault = None
        self._request = None          # armed REQUEST_DEV_DEP_MSG_IN: dict(tag, size, term)
        self._in_fifo: list[list] = []  # [bytes, ready_at, tag]
        self._in_tag = 0
        self._in_sent = 0             # bytes of the current Bulk-IN transfer already read
        self._abort_in = None         # bytes sent before an abort, while the abort is pending
        self._abort_out_bytes = 0
        self._intr: list[bytes] = []

    def _unplug(self, *, replug: bool) -> None:
        with self._cv:
            self._plugged = False
            self._claims.clear()
            self._reset_transfer_state()
            self._cv.notify_all()
            if replug:
                self._generation += 1
                self._address = 5 + self._generation % 100
                self._dev = _DeviceId(1, self._address, self._generation)
                self._configuration = CONFIG_VALUE
                self._plugged = True

    # ------------------------------------------------------------ IBackend: handles
    def open_device(self, dev):
        with self._cv:
            if not self._plugged or dev is not self._dev:
                raise _usb_error("no_device")
            return _Handle(dev)

    def close_device(self, dev_handle):
        with self._cv:
            for intf in list(dev_handle.claimed):
                if self._claims.get(intf) is dev_handle:
                    del self._claims[intf]
            dev_handle.claimed.clear()
            dev_handle.open = False

    def _live(self, handle) -> None:
        if not handle.open or not self._plugged or handle.dev is not self._dev:
            raise _usb_error("no_device")

    def set_configuration(self, dev_handle, config_value):
        with self._cv:
            self._live(dev_handle)
            if config_value not in (0, CONFIG_VALUE):
                raise _usb_error("not_found")
            self._configuration = config_value
            self._reset_transfer_state()

    def get_configuration(self, dev_handle):
        with self._cv:
            self._live(dev_handle)
            return self._configuration

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        with self._cv:
            self._live(dev_handle)
            if intf != INTERFACE_NUMBER or altsetting != 0:
                raise _usb_error("not_found")

    def claim_interface(self, dev_handle, intf):
        with self._cv:
            self._live(dev_handle)
            if intf != INTERFACE_NUMBER or self._configuration != CONFIG_VALUE:
                raise _usb_error("not_found")
            owner = self._claims.get(intf)
            if owner is not None and owner is not dev_handle:
                raise _usb_error("busy")
            self._claims[intf] = dev_handle
            dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle, intf):
        with self._cv:
            self._live(dev_handle)
            if intf not in dev_handle.claimed:
                raise _usb_error("not_found")
            dev_handle.claimed.discard(intf)
            if self._claims.get(intf) is dev_handle:
                del self._claims[intf]

    def is_kernel_driver_active(self, dev_handle, intf):
        with self._cv:
            self._live(dev_handle)
            return False

    def detach_kernel_driver(self, dev_handle, intf):
        with self._cv:
            self._live(dev_handle)
            raise _usb_error("not_found")  # libusb: no kernel driver attached

    def attach_kernel_driver(self, dev_handle, intf):
        with self._cv:
            self._live(dev_handle)

    def clear_halt(self, dev_handle, ep):
        with self._cv:
            self._live(dev_handle)
            self._halted.discard(ep)
            self.log.append(("ctrl", 0x02, 1, 0, ep, 0))  # CLEAR_FEATURE(ENDPOINT_HALT)

    def reset_device(self, dev_handle):
        with self._cv:
            self._live(dev_handle)
            self._reset_transfer_state()

    def _claimed(self, handle, intf) -> None:
        self._live(handle)
        if self._claims.get(intf) is not handle:
            raise _usb_error("not_found")

    # ------------------------------------------------------------ IBackend: bulk / interrupt
    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        payload = bytes(data)
        with self._cv:
            self._claimed(dev_handle, intf)
            if ep != EP_BULK_OUT:
                raise _usb_error("invalid")
            if ep in self._halted:
                raise _usb_error("pipe")
            self.log.append(("bulk_out", ep, payload))
            self._receive(payload)   # may raise pipe (STALL) or no_device (disconnect fault)
            self._cv.notify_all()
            return len(payload)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = None if not timeout else time.monotonic() + timeout / 1000.0
        with self._cv:
            while True:
                self._claimed(dev_handle, intf)
                if ep != EP_BULK_IN:
                    raise _usb_error("invalid")
                if ep in self._halted:
                    raise _usb_error("pipe")
                now = time.monotonic()
                if self._in_fifo and self._in_fifo[0][1] <= now:
                    return self._deliver(buff)
                waits = [deadline - now] if deadline is not None else []
                if self._in_fifo:
                    waits.append(self._in_fifo[0][1] - now)
                if deadline is not None and now >= deadline:
                    raise _usb_error("timeout")
                self._cv.wait(min(waits) if waits else None)

    def _deliver(self, buff) -> int:
        head = self._in_fifo[0]
        data = head[0]
        n = min(len(buff) * buff.itemsize, len(data))
        chunk, head[0] = data[:n], data[n:]
        buff[:n] = array.array("B", chunk)
        self._in_sent += n
        self.log.append(("bulk_in", EP_BULK_IN, chunk))
        if not head[0]:
            self._in_fifo.pop(0)
            if self._abort_in is None:
                self._in_sent = 0
        return n

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = None if not timeout else time.monotonic() + timeout / 1000.0
        with self._cv:
            while True:
                self._claimed(dev_handle, intf)
                if ep != EP_INTR_IN:
                    raise _usb_error("invalid")
                if self._intr:
                    data = self._intr.pop(0)
                    n = min(len(buff), len(data))
                    buff[:n] = array.array("B", data[:n])
                    self.log.append(("intr_in", ep, data[:n]))
                    return n
                now = time.monotonic()
                if deadline is not None and now >= deadline:
                    raise _usb_error("timeout")
                self._cv.wait(None if deadline is None else deadline - now)

    def intr_write(self, dev_handle, ep, intf, data, timeout):
        raise _usb_error("invalid")

    # ------------------------------------------------------------ device: Bulk-OUT
    def _receive(self, data: bytes) -> None:
        pos = 0
        while pos < len(data):
            if self._out_hdr is None:
                if self._out_pad:
                    # alignment bytes after the previous transfer's data
                    skip = min(self._out_pad, len(data) - pos)
                    pos += skip
                    self._out_pad -= skip
                    continue
                if len(data) - pos < 12:
                    self._stall()
                header = data[pos:pos + 12]
                pos += 12
                msgid, tag, inv, reserved, size, attrs = struct.unpack("<BBBBIB", header[:9])
                if tag == 0 or inv != (~tag & 0xFF) or reserved != 0:
                    self._stall()
                self._out_tag = tag
                if msgid == DEV_DEP_MSG_OUT:
                    if size == 0:
                        self._stall()
                    self._out_hdr = (msgid, tag, size, attrs)
                    self._out_got = 0
                elif msgid == REQUEST_DEV_DEP_MSG_IN:
                    if size == 0:
                        self._stall()
                    term = header[9] if attrs & 0x02 else None
                    self._arm_request(tag, size, term)
                    # a request has no data; the rest of this transfer (if any) is alignment
                    pos = len(data)
                else:
                    self._stall()  # vendor specific / TRIGGER: not supported by this device
                continue
            msgid, tag, size, attrs = self._out_hdr
            take = min(size - self._out_got, len(data) - pos)
            self._msg += data[pos:pos + take]
            self._out_got += take
            pos += take
            if self._out_got == size:
                self._out_hdr = None
                self._out_pad = (-size) % 4
                if attrs & 0x01:
                    message, self._msg = bytes(self._msg), bytearray()
                    self._execute(message)
        # the transfer ended: alignment bytes it did not carry are not expected any more
        self._out_pad = 0

    def _stall(self) -> None:
        self._halted.add(EP_BULK_OUT)
        self._out_hdr = None
        self._msg = bytearray()
        raise _usb_error("pipe")

    def _execute(self, message_bytes: bytes) -> None:
        text = message_bytes.decode("ascii", errors="replace").strip("\r\n")
        instrument = self.instrument
        headers = SyncInstrument.headers(text)
        fault = self.faults.take(headers[0]) if headers else None
        if fault is not None and fault.kind in ("close", "unplug"):
            self._unplug(replug=fault.kind == "close")
            raise _usb_error("no_device")
        if self._output:
            # IEEE 488.2: a new message while a response is unread interrupts the query
            self._output.clear()
            self._output_fault = None
            instrument.push_error(-410)
        if fault is not None and fault.kind == "error":
            instrument.push_error(int(fault.code))
            return
        responses = instrument.execute(text, message_available=bool(self._output))
        if responses:
            self._output += (";".join(responses) + "\n").encode("ascii")
            self._output_fault = fault
        self._fulfil()

    # ------------------------------------------------------------ device: Bulk-IN
    def _arm_request(self, tag: int, size: int, term) -> None:
        self._request = {"tag": tag, "size": size, "term": term, "dropped": False}
        self._in_tag = tag
        self._fulfil()

    def _fulfil(self) -> None:
        req = self._request
        if req is None or req["dropped"] or not self._output:
            return
        fault, self._output_fault = self._output_fault, None
        if fault is not None and fault.kind == "drop_reply":
            self._output.clear()
            req["dropped"] = True   # the transfer stays "in progress" and never completes
            return
        n = min(req["size"], len(self._output))
        term_hit = False
        if req["term"] is not None:
            idx = self._output.find(bytes([req["term"]]), 0, n)
            if idx >= 0:
                n, term_hit = idx + 1, True
        chunk = bytes(self._output[:n])
        del self._output[:n]
        eom = not self._output
        attrs = (0x01 if eom else 0) | (0x02 if term_hit else 0)
        tag = req["tag"]
        transfer = struct.pack("<BBBBIBBBB", DEV_DEP_MSG_IN, tag, ~tag & 0xFF, 0, len(chunk),
                               attrs, 0, 0, 0) + chunk + bytes((-len(chunk)) % 4)
        ready = time.monotonic()
        if fault is not None and fault.kind == "garbage":
            transfer = _GARBAGE
        if fault is not None and fault.kind == "delay":
            ready += fault.delay_s
        self._in_fifo.append([transfer, ready, tag])
        self._request = None
        self._cv.notify_all()

    # ------------------------------------------------------------ IBackend: control
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        with self._cv:
            self._live(dev_handle)
            direction_in = bool(bmRequestType & 0x80)
            length = len(data) * data.itemsize
            self.log.append(("ctrl", bmRequestType, bRequest, wValue, wIndex,
                             length if direction_in else bytes(data)))
            kind = (bmRequestType >> 5) & 0x03
            if kind == 0:
                reply = self._standard_request(bmRequestType, bRequest, wValue, wIndex, length)
            elif kind == 1:
                reply = self._class_request(bmRequestType, bRequest, wValue, wIndex, length)
            else:
                raise _usb_error("pipe")
            self._cv.notify_all()
            if not direction_in:
                return length
            n = min(length, len(reply))
            data[:n] = array.array("B", reply[:n])
            return n

    def _standard_request(self, rtype, req, value, index, length) -> bytes:
        if rtype == 0x80 and req == 6:                     # GET_DESCRIPTOR
            return self._descriptor_bytes(value >> 8, value & 0xFF, index)
        if rtype in (0x80, 0x81) and req == 0:             # GET_STATUS device / interface
            return b"\x00\x00"
        if rtype == 0x82 and req == 0:                     # GET_STATUS endpoint
            if index not in (EP_BULK_OUT, EP_BULK_IN, EP_INTR_IN):
                raise _usb_error("pipe")
            return bytes([1 if index in self._halted else 0, 0])
        if rtype == 0x02 and req in (1, 3) and value == 0:  # CLEAR_FEATURE / SET_FEATURE(HALT)
            if index not in (EP_BULK_OUT, EP_BULK_IN, EP_INTR_IN):
                raise _usb_error("pipe")
            if req == 1:
                self._halted.discard(index)
            else:
                self._halted.add(index)
            return b""
        if rtype == 0x80 and req == 8:                     # GET_CONFIGURATION
            return bytes([self._configuration])
        if rtype == 0x00 and req == 9:                     # SET_CONFIGURATION
            if value not in (0, CONFIG_VALUE):
                raise _usb_error("pipe")
            self._configuration = value
            self._reset_transfer_state()
            return b""
        if rtype == 0x81 and req == 10 and index == INTERFACE_NUMBER:  # GET_INTERFACE
            return b"\x00"
        if rtype == 0x01 and req == 11 and index == INTERFACE_NUMBER and value == 0:  # SET_INTERFACE
            return b""
        raise _usb_error("pipe")

    def _class_request(self, rtype, req, value, index, length) -> bytes:
        def expect(want_type, want_index, want_length):
            if rtype != want_type or index != want_index or length != want_length:
                raise _usb_error("pipe")

        if req == GET_CAPABILITIES:
            expect(0xA1, INTERFACE_NUMBER, 0x18)
            # USBTMC 1.0 table 37 + USB488 table 8: bcdUSBTMC 1.00, TermChar supported,
            # bcdUSB488 1.00, no USB488 optional capabilities
            return bytes([STATUS_SUCCESS, 0, 0x00, 0x01, 0x00, 0x01, 0, 0, 0, 0, 0, 0,
                          0x00, 0x01, 0x00, 0x00, 0, 0, 0, 0, 0, 0, 0, 0])
        if req == INITIATE_CLEAR:
            expect(0xA1, INTERFACE_NUMBER, 1)
            self._out_hdr = None
            self._out_pad = 0
            self._msg = bytearray()
            self._output.clear()
            self._output_fault = None
            self._request = None
            self._in_fifo.clear()
            self._in_sent = 0
            self._abort_in = None
            return bytes([STATUS_SUCCESS])
        if req == CHECK_CLEAR_STATUS:
            expect(0xA1, INTERFACE_NUMBER, 2)
            return bytes([STATUS_SUCCESS, 0])
        if req == INITIATE_ABORT_BULK_IN:
            expect(0xA2, EP_BULK_IN, 2)
            tag = value & 0xFF
            in_progress = self._request is not None or bool(self._in_fifo)
            if not in_progress:
                return bytes([STATUS_FAILED, self._in_tag])
            if tag != self._in_tag:
                return bytes([STATUS_TRANSFER_NOT_IN_PROGRESS, self._in_tag])
            self._request = None
            self._in_fifo.clear()
            self._abort_in = self._in_sent
            self._in_fifo.append([b"", time.monotonic(), tag])  # the short packet ending the transfer
            return bytes([STATUS_SUCCESS, tag])
        if req == CHECK_ABORT_BULK_IN_STATUS:
            expect(0xA2, EP_BULK_IN, 8)
            sent = self._abort_in or 0
            if self._in_fifo:
                return bytes([STATUS_PENDING, 0x01, 0, 0]) + struct.pack("<I", sent)
            self._abort_in = None
            self._in_sent = 0
            return bytes([STATUS_SUCCESS, 0x00, 0, 0]) + struct.pack("<I", sent)
        if req == INITIATE_ABORT_BULK_OUT:
            expect(0xA2, EP_BULK_OUT, 2)
            tag = value & 0xFF
            if self._out_hdr is None:
                return bytes([STATUS_FAILED, self._out_tag])
            if tag != self._out_hdr[1]:
                return bytes([STATUS_TRANSFER_NOT_IN_PROGRESS, self._out_tag])
            self._abort_out_bytes = self._out_got
            self._out_hdr = None
            self._msg = bytearray()
            self._halted.add(EP_BULK_OUT)   # USBTMC 1.0, 4.2.1.2: halt Bulk-OUT before answering
            return bytes([STATUS_SUCCESS, tag])
        if req == CHECK_ABORT_BULK_OUT_STATUS:
            expect(0xA2, EP_BULK_OUT, 8)
            return bytes([STATUS_SUCCESS, 0, 0, 0]) + struct.pack("<I", self._abort_out_bytes)
        if req == READ_STATUS_BYTE:
            expect(0xA1, INTERFACE_NUMBER, 3)
            tag = value & 0x7F
            if not 2 <= tag <= 127:
                raise _usb_error("pipe")
            stb = self.instrument.status_byte(bool(self._output) or bool(self._in_fifo))
            # USB488 3.4.2: with an interrupt-IN endpoint the status byte comes as a notification
            self._intr.append(bytes([0x80 | tag, stb]))
            return bytes([STATUS_SUCCESS, tag, 0x00])
        raise _usb_error("pipe")
