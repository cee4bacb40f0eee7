"""USBTMC 1.0 transport over pyusb: bulk message framing, abort and clear.

Implements the host side of the USB Test and Measurement Class specification
(USBTMC 1.0, USB-IF 2003):

* Bulk-OUT header (section 3.2, tables 1-4): ``MsgID, bTag, ~bTag, 0x00``,
  four-byte little-endian TransferSize, bmTransferAttributes (D0 = EOM for
  DEV_DEP_MSG_OUT; D1 = TermCharEnabled and byte 9 = TermChar for
  REQUEST_DEV_DEP_MSG_IN), then reserved bytes; the message bytes follow and
  the transfer is padded with zeros to a multiple of 4 bytes.
* bTag (table 1): 1..255, incremented for every Bulk-OUT header, never 0;
  the Bulk-IN DEV_DEP_MSG_IN header (tables 9-11) must echo the bTag of the
  REQUEST_DEV_DEP_MSG_IN it answers.
* class requests (section 4.2.1, table 15): GET_CAPABILITIES (7) when the
  interface is opened; after a Bulk-IN timeout INITIATE_ABORT_BULK_IN (3),
  read to the short packet, then CHECK_ABORT_BULK_IN_STATUS (4) until not
  PENDING; after a Bulk-OUT timeout INITIATE_ABORT_BULK_OUT (1),
  CHECK_ABORT_BULK_OUT_STATUS (2) and CLEAR_FEATURE(ENDPOINT_HALT);
  :meth:`UsbtmcTransport.clear` is INITIATE_CLEAR (5) / CHECK_CLEAR_STATUS (6)
  followed by CLEAR_FEATURE(ENDPOINT_HALT) on Bulk-OUT.

One lock per connection: a query's write and read happen under it, so a reply
is always the one to its own request (the bTag check enforces it).  Every USB
call has a timeout.  pyusb errors never leave this module: a timeout becomes
:class:`~drivers.errors.DeviceTimeout` (after the abort sequence), a vanished
device :class:`~drivers.errors.ConnectionLost` (after one attempt to find and
reopen it), a malformed transfer :class:`~drivers.errors.ProtocolError`.
"""
from __future__ import annotations

import errno
import struct
import threading
import time

import usb.core
import usb.util

from .errors import ConnectionLost, DeviceError, DeviceTimeout, ProtocolError

USBTMC_CLASS = 0xFE
USBTMC_SUBCLASS = 0x03

# USBTMC 1.0 table 2 / USB488 table 2: MsgID values
DEV_DEP_MSG_OUT = 1
REQUEST_DEV_DEP_MSG_IN = 2
DEV_DEP_MSG_IN = 2

# USBTMC 1.0 table 15 / USB488 table 9: class request codes
INITIATE_ABORT_BULK_OUT = 1
CHECK_ABORT_BULK_OUT_STATUS = 2
INITIATE_ABORT_BULK_IN = 3
CHECK_ABORT_BULK_IN_STATUS = 4
INITIATE_CLEAR = 5
CHECK_CLEAR_STATUS = 6
GET_CAPABILITIES = 7
READ_STATUS_BYTE = 128

# USBTMC 1.0 table 16: USBTMC_status values
STATUS_SUCCESS = 0x01
STATUS_PENDING = 0x02
STATUS_FAILED = 0x80
STATUS_TRANSFER_NOT_IN_PROGRESS = 0x81

# bmRequestType for class requests: IN | class | interface, IN | class | endpoint
_RT_INTERFACE = 0xA1
_RT_ENDPOINT = 0xA2

_GONE_ERRNOS = {errno.ENODEV, errno.EIO, errno.ENOENT, errno.ESHUTDOWN}
_GONE_CODES = {-1, -4, -5}  # libusb IO, NO_DEVICE, NOT_FOUND


def bulk_out_header(msg_id: int, tag: int, transfer_size: int, attributes: int = 0,
                    term_char: int = 0) -> bytes:
    """The 12-byte USBTMC Bulk-OUT header (USBTMC 1.0 tables 1, 3 and 4)."""
    if not 1 <= tag <= 255:
        raise ValueError(f"bTag must be 1..255, got {tag}")
    return struct.pack("<BBBBIBBBB", msg_id, tag, ~tag & 0xFF, 0, transfer_size,
                       attributes, term_char, 0, 0)


def dev_dep_msg_out(tag: int, data: bytes, eom: bool = True) -> bytes:
    """One DEV_DEP_MSG_OUT transfer: header, message bytes, zero padding to 4 bytes."""
    if not data:
        raise ValueError("a DEV_DEP_MSG_OUT transfer carries at least one byte")
    return bulk_out_header(DEV_DEP_MSG_OUT, tag, len(data), 0x01 if eom else 0x00) + \
        bytes(data) + bytes((-len(data)) % 4)


def request_dev_dep_msg_in(tag: int, transfer_size: int, term_char: int | None = None) -> bytes:
    """One REQUEST_DEV_DEP_MSG_IN transfer (12 bytes, already a multiple of 4)."""
    if term_char is None:
        return bulk_out_header(REQUEST_DEV_DEP_MSG_IN, tag, transfer_size, 0x00, 0)
    return bulk_out_header(REQUEST_DEV_DEP_MSG_IN, tag, transfer_size, 0x02, term_char)


class Capabilities:
    """Parsed GET_CAPABILITIES response (USBTMC 1.0 table 37; USB488 table 8)."""

    def __init__(self, raw: bytes):
        if len(raw) != 0x18 or raw[0] != STATUS_SUCCESS:
            raise ProtocolError("bad GET_CAPABILITIES response", raw)
        self.raw = bytes(raw)
        self.bcd_usbtmc = raw[2] | (raw[3] << 8)
        self.indicator_pulse = bool(raw[4] & 0x04)
        self.talk_only = bool(raw[4] & 0x02)
        self.listen_only = bool(raw[4] & 0x01)
        self.term_char = bool(raw[5] & 0x01)
        self.bcd_usb488 = raw[12] | (raw[13] << 8)


def _find_bulk(intf, direction):
    return usb.util.find_descriptor(
        intf, custom_match=lambda e: usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
        and usb.util.endpoint_direction(e.bEndpointAddress) == direction)


class UsbtmcTransport:
    """Host side of one USBTMC interface.

    Parameters
    ----------
    vendor_id, product_id : int, optional
        USB ids to match.
    serial_number : str, optional
        iSerialNumber string to match (several identical instruments on one host).
    backend : usb.backend.IBackend, optional
        pyusb backend (a simulator in tests; None lets pyusb pick libusb).
    timeout_s : float
        Budget for one write or one read, seconds.
    max_read_size : int
        TransferSize asked for in each REQUEST_DEV_DEP_MSG_IN, bytes.
    term_char : int, optional
        Ask the device to end each Bulk-IN transfer at this byte (only if it
        reports TermChar support).

    The first USBTMC interface (class 0xFE, subclass 0x03) of the first matching
    device is used.
    """

    def __init__(self, *, vendor_id: int | None = None, product_id: int | None = None,
                 serial_number: str | None = None, backend=None, timeout_s: float = 2.0,
                 max_read_size: int = 65536, term_char: int | None = None):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if not 1 <= int(max_read_size) <= 0xFFFFFFFF:
            raise ValueError(f"max_read_size must be 1..2**32-1, got {max_read_size!r}")
        self.vendor_id, self.product_id, self.serial_number = vendor_id, product_id, serial_number
        self.backend = backend
        self.timeout_s = float(timeout_s)
        self.max_read_size = int(max_read_size)
        self.term_char = term_char
        self.lock = threading.RLock()
        self._tag = 0
        self._dev = None
        self._closed = False
        self.capabilities: Capabilities | None = None
        with self.lock:
            self._connect()

    # ------------------------------------------------------------ connection
    def describe(self) -> str:
        parts = []
        if self.vendor_id is not None:
            parts.append(f"idVendor=0x{self.vendor_id:04x}")
        if self.product_id is not None:
            parts.append(f"idProduct=0x{self.product_id:04x}")
        if self.serial_number is not None:
            parts.append(f"serial={self.serial_number!r}")
        return "USBTMC device " + (" ".join(parts) if parts else "(any)")

    def _matches(self, dev) -> bool:
        if self.vendor_id is not None and dev.idVendor != self.vendor_id:
            return False
        if self.product_id is not None and dev.idProduct != self.product_id:
            return False
        if not any(i.bInterfaceClass == USBTMC_CLASS and i.bInterfaceSubClass == USBTMC_SUBCLASS
                   for cfg in dev for i in cfg):
            return False
        if self.serial_number is not None:
            try:
                if dev.serial_number != self.serial_number:
                    return False
            except (usb.core.USBError, ValueError):
                return False
        return True

    def _connect(self) -> None:
        try:
            dev = usb.core.find(backend=self.backend, custom_match=self._matches)
        except usb.core.NoBackendError as exc:
            raise ConnectionLost(f"no pyusb backend (libusb) available to look for {self.describe()}") from exc
        except (usb.core.USBError, ValueError) as exc:
            raise ConnectionLost(f"{self.describe()}: enumeration failed ({exc})") from exc
        if dev is None:
            raise ConnectionLost(f"{self.describe()} not found")
        try:
            try:
                cfg = dev.get_active_configuration()
            except usb.core.USBError:
                dev.set_configuration()
                cfg = dev.get_active_configuration()
            intf = usb.util.find_descriptor(cfg, bInterfaceClass=USBTMC_CLASS,
                                            bInterfaceSubClass=USBTMC_SUBCLASS)
            try:
                if dev.is_kernel_driver_active(intf.bInterfaceNumber):
                    dev.detach_kernel_driver(intf.bInterfaceNumber)
            except (NotImplementedError, usb.core.USBError):
                pass  # backends without kernel drivers (or none attached)
            usb.util.claim_interface(dev, intf)
            self._intf = intf
            self._intf_number = intf.bInterfaceNumber
            self._ep_out = _find_bulk(intf, usb.util.ENDPOINT_OUT)
            self._ep_in = _find_bulk(intf, usb.util.ENDPOINT_IN)
            if self._ep_out is None or self._ep_in is None:
                raise ProtocolError(f"{self.describe()}: USBTMC interface without bulk endpoints", b"")
            self._in_packet = self._ep_in.wMaxPacketSize
            self._dev = dev
            raw = self._control(_RT_INTERFACE, GET_CAPABILITIES, 0, self._intf_number, 0x18)
            self.capabilities = Capabilities(raw)
            if self.term_char is not None and not self.capabilities.term_char:
                # USBTMC 1.0 table 4: TermCharEnabled must be 0 unless the device supports it
                self._release(dev)
                raise ValueError(f"{self.describe()} does not support TermChar; use term_char=None")
        except usb.core.USBError as exc:
            self._release(dev)
            raise ConnectionLost(f"{self.describe()}: cannot open ({exc})") from exc
        except ProtocolError:
            self._release(dev)
            raise

    def _release(self, dev) -> None:
        self._dev = None
        if dev is None:
            return
        try:
            usb.util.dispose_resources(dev)
        except (usb.core.USBError, ValueError):
            pass

    def close(self) -> None:
        """Release the interface and the device (idempotent)."""
        with self.lock:
            self._closed = True
            self._release(self._dev)

    # ------------------------------------------------------------ low level
    def _next_tag(self) -> int:
        self._tag = self._tag % 255 + 1    # 1..255, never 0
        return self._tag

    @staticmethod
    def _ms(deadline: float) -> int:
        return max(1, int((deadline - time.monotonic()) * 1000))

    def _control(self, request_type: int, request: int, value: int, index: int, length: int,
                 timeout_ms: int | None = None) -> bytes:
        return bytes(self._dev.ctrl_transfer(request_type, request, value, index, length,
                                             timeout_ms or int(self.timeout_s * 1000)))

    @staticmethod
    def _is_gone(exc: usb.core.USBError) -> bool:
        return exc.errno in _GONE_ERRNOS or exc.backend_error_code in _GONE_CODES

    def _with_reconnect(self, operation):
        """Run ``operation()``; if the device vanished, find and reopen it once and run it again."""
        with self.lock:
            if self._closed:
                raise ConnectionLost(f"{self.describe()}: transport is closed")
            for attempt in (0, 1):
                try:
                    if self._dev is None:
                        self._connect()
                    return operation()
                except usb.core.USBTimeoutError as exc:   # handled inside operations; safety net
                    raise DeviceTimeout(f"{self.describe()}: {exc}") from exc
                except usb.core.USBError as exc:
                    if not self._is_gone(exc):
                        # e.g. a STALLed endpoint: clear the halt and the device's buffers, then report
                        if exc.errno == errno.EPIPE or exc.backend_error_code == -9:
                            self._recover_quietly(lambda: self._dev.clear_halt(self._ep_in.bEndpointAddress))
                        self._resync()
                        raise ProtocolError(f"{self.describe()}: USB error {exc}", b"") from exc
                    self._release(self._dev)
                    if attempt == 1:
                        raise ConnectionLost(f"{self.describe()}: connection lost ({exc})") from exc
                except ConnectionLost:
                    if attempt == 1:
                        raise
                    self._release(self._dev)

    # ------------------------------------------------------------ messages
    def write(self, message: bytes) -> None:
        """Send one device-dependent message (DEV_DEP_MSG_OUT with EOM on its last transfer)."""
        message = bytes(message)
        if not message:
            raise ValueError("cannot send an empty message")
        self._with_reconnect(lambda: self._write(message))

    def read(self) -> bytes:
        """Read one complete response message (REQUEST_DEV_DEP_MSG_IN until EOM)."""
        return self._with_reconnect(self._read)

    def query(self, message: bytes) -> bytes:
        """Write ``message`` and read its response under the connection lock."""
        message = bytes(message)
        if not message:
            raise ValueError("cannot send an empty message")

        def exchange():
            self._write(message)
            return self._read()
        return self._with_reconnect(exchange)

    def _write(self, message: bytes, chunk: int = 1 << 20) -> None:
        deadline = time.monotonic() + self.timeout_s
        for start in range(0, len(message), chunk):
            part = message[start:start + chunk]
            tag = self._next_tag()
            frame = dev_dep_msg_out(tag, part, eom=start + chunk >= len(message))
            try:
                self._dev.write(self._ep_out.bEndpointAddress, frame, self._ms(deadline))
            except usb.core.USBTimeoutError as exc:
                self._abort_bulk_out(tag)
                raise DeviceTimeout(f"{self.describe()}: write not accepted within "
                                    f"{self.timeout_s:g} s") from exc
            except usb.core.USBError as exc:
                if exc.errno == errno.EPIPE or exc.backend_error_code == -9:
                    self._recover_quietly(lambda: self._dev.clear_halt(self._ep_out.bEndpointAddress))
                    raise ProtocolError(f"{self.describe()}: device halted Bulk-OUT "
                                        f"(rejected the transfer)", frame[:12]) from exc
                raise

    def _read(self) -> bytes:
        deadline = time.monotonic() + self.timeout_s
        out = bytearray()
        while True:
            tag = self._next_tag()
            try:
                self._dev.write(self._ep_out.bEndpointAddress,
                                request_dev_dep_msg_in(tag, self.max_read_size, self.term_char),
                                self._ms(deadline))
            except usb.core.USBTimeoutError as exc:
                self._abort_bulk_out(tag)
                raise DeviceTimeout(f"{self.describe()}: read request not accepted") from exc
            data, eom = self._read_transfer(tag, deadline)
            out += data
            if eom:
                return bytes(out)
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.describe()}: response not complete within {self.timeout_s:g} s")

    def _read_transfer(self, tag: int, deadline: float) -> tuple[bytes, bool]:
        packet = self._in_packet
        size = -(-(12 + self.max_read_size + 3) // packet) * packet  # whole packets, room for padding
        raw = bytearray()
        try:
            raw += self._dev.read(self._ep_in.bEndpointAddress, size, self._ms(deadline))
            if len(raw) < 12:
                self._resync()
                raise ProtocolError(f"{self.describe()}: Bulk-IN transfer shorter than a header", raw)
            msg_id, rtag, inv, reserved, length, attrs = struct.unpack("<BBBBIB", raw[:9])
            if msg_id != DEV_DEP_MSG_IN or inv != (~rtag & 0xFF) or reserved != 0:
                self._resync()
                raise ProtocolError(f"{self.describe()}: not a DEV_DEP_MSG_IN header", raw)
            if rtag != tag:
                self._resync()
                raise ProtocolError(f"{self.describe()}: reply bTag {rtag} does not match request {tag}", raw)
            if length > self.max_read_size:
                self._resync()
                raise ProtocolError(f"{self.describe()}: TransferSize {length} exceeds the request", raw)
            while len(raw) < 12 + length:   # a transfer longer than one read
                more = self._dev.read(self._ep_in.bEndpointAddress, size, self._ms(deadline))
                if len(more) == 0:
                    self._resync()
                    raise ProtocolError(f"{self.describe()}: Bulk-IN transfer ended early", raw)
                raw += more
        except usb.core.USBTimeoutError as exc:
            self._abort_bulk_in(tag)
            raise DeviceTimeout(f"{self.describe()}: no response within {self.timeout_s:g} s") from exc
        return bytes(raw[12:12 + length]), bool(attrs & 0x01)

    # ------------------------------------------------------------ recovery
    def _recover_quietly(self, step) -> None:
        try:
            step()
        except (usb.core.USBError, ProtocolError):
            pass

    def _resync(self) -> None:
        self._recover_quietly(self._clear)

    def _drain_in(self, deadline: float) -> None:
        """Read Bulk-IN until a short packet (USBTMC 1.0, 4.2.1.4)."""
        packet = self._in_packet
        while time.monotonic() < deadline:
            got = self._dev.read(self._ep_in.bEndpointAddress, packet, self._ms(deadline))
            if len(got) < packet:
                return

    def _abort_bulk_in(self, tag: int) -> None:
        """INITIATE_ABORT_BULK_IN for ``tag``, then drain and poll CHECK_ABORT_BULK_IN_STATUS."""
        deadline = time.monotonic() + self.timeout_s

        def sequence():
            ep = self._ep_in.bEndpointAddress
            status = self._control(_RT_ENDPOINT, INITIATE_ABORT_BULK_IN, tag, ep, 2)[0]
            if status == STATUS_FAILED:
                return                          # nothing in progress: nothing to abort
            if status != STATUS_SUCCESS:
                self._clear()
                return
            self._drain_in(deadline)
            while time.monotonic() < deadline:
                check = self._control(_RT_ENDPOINT, CHECK_ABORT_BULK_IN_STATUS, 0, ep, 8)
                if check[0] != STATUS_PENDING:
                    return
                if check[1] & 0x01:
                    self._drain_in(deadline)
                else:
                    time.sleep(0.005)
        self._recover_quietly(sequence)

    def _abort_bulk_out(self, tag: int) -> None:
        """INITIATE_ABORT_BULK_OUT for ``tag``, poll its status, clear the endpoint halt."""
        deadline = time.monotonic() + self.timeout_s

        def sequence():
            ep = self._ep_out.bEndpointAddress
            status = self._control(_RT_ENDPOINT, INITIATE_ABORT_BULK_OUT, tag, ep, 2)[0]
            if status != STATUS_SUCCESS:
                return
            while time.monotonic() < deadline:
                if self._control(_RT_ENDPOINT, CHECK_ABORT_BULK_OUT_STATUS, 0, ep, 8)[0] != STATUS_PENDING:
                    break
                time.sleep(0.005)
            self._dev.clear_halt(ep)
        self._recover_quietly(sequence)

    def _clear(self) -> None:
        deadline = time.monotonic() + self.timeout_s
        status = self._control(_RT_INTERFACE, INITIATE_CLEAR, 0, self._intf_number, 1)[0]
        if status != STATUS_SUCCESS:
            raise DeviceError(status, "INITIATE_CLEAR refused", command="INITIATE_CLEAR",
                              device=self.describe())
        while True:
            check = self._control(_RT_INTERFACE, CHECK_CLEAR_STATUS, 0, self._intf_number, 2)
            if check[0] != STATUS_PENDING:
                break
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"{self.describe()}: clear still pending after {self.timeout_s:g} s")
            if check[1] & 0x01:
                self._drain_in(deadline)
            else:
                time.sleep(0.005)
        self._dev.clear_halt(self._ep_out.bEndpointAddress)

    def clear(self) -> None:
        """Device clear: INITIATE_CLEAR, CHECK_CLEAR_STATUS until done, CLEAR_FEATURE on Bulk-OUT."""
        self._with_reconnect(self._clear)
