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
import errno
import math
import struct
import threading
import time
from types import SimpleNamespace

import usb.backend
from usb.core import USBError, USBTimeoutError

from .faults import COMMON_KINDS, FaultInjector
from .state import LabState

# ---------------------------------------------------------------- USB constants
# libusb error codes as pyusb's libusb1 backend reports them (code, errno)
_LIBUSB = {
    "io": (-1, errno.EIO, "Input/Output Error"),
    "invalid": (-2, errno.EINVAL, "Invalid parameter"),
    "no_device": (-4, errno.ENODEV, "No such device (it may have been disconnected)"),
    "not_found": (-5, errno.ENOENT, "Entity not found"),
    "busy": (-6, errno.EBUSY, "Resource busy"),
    "timeout": (-7, errno.ETIMEDOUT, "Operation timed out"),
    "pipe": (-9, errno.EPIPE, "Pipe error"),
}


def _usb_error(kind: str) -> USBError:
    code, err, text = _LIBUSB[kind]
    cls = USBTimeoutError if kind == "timeout" else USBError
    return cls(text, code, err)


EP_BULK_OUT = 0x02
EP_BULK_IN = 0x81
EP_INTR_IN = 0x83
MAX_PACKET = 64          # full speed bulk endpoints
INTERFACE_NUMBER = 0
CONFIG_VALUE = 1

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

_GARBAGE = bytes([0x7F, 0x00, 0x13, 0x37]) + b"\xde\xad\xbe\xef" * 3

# ---------------------------------------------------------------- SCPI error texts
# SCPI-99 volume 2, chapter 21 (error/event queue): standard codes and texts
SCPI_ERRORS = {
    0: "No error",
    -100: "Command error",
    -102: "Syntax error",
    -104: "Data type error",
    -108: "Parameter not allowed",
    -109: "Missing parameter",
    -113: "Undefined header",
    -200: "Execution error",
    -222: "Data out of range",
    -224: "Illegal parameter value",
    -240: "Hardware error",
    -300: "Device-specific error",
    -310: "System error",
    -350: "Queue overflow",
    -410: "Query INTERRUPTED",
    -420: "Query UNTERMINATED",
}

COMMANDS_DOC = """\
*IDN?                    -> "STREAKLAB,SLS-575SIM,<serial>,<firmware>"
*RST                     system period 12.5 ns (80 MHz), all delays 0, widths 10 ns, output off
*CLS                     clear the error queue and the event status register
*OPC? / *OPC / *WAI      operation complete ("1")
*ESR? / *STB? / *TST?    event status register / status byte / self test ("0")
SYSTem:ERRor[:NEXT]?     -> <code>,"<text>"  (0,"No error" when the queue is empty)
:PULSe0:PERiod <s> / ?   system (repetition) period, 5 ns .. 1000 s
:PULSe0:STATe ON|OFF / ? system output enable (all channels)
:PULSe<n>:DELay <s> / ?  channel n = 1..4 delay after T0, 0 .. 1 ms, 0.1 ps resolution
:PULSe<n>:WIDTh <s> / ?  channel n pulse width, 1 ns .. 1 ms
:PULSe<n>:STATe ON|OFF / ? channel n enable
"""

_PERIOD_RANGE_S = (5e-9, 1000.0)
_DELAY_RANGE_S = (0.0, 1e-3)
_WIDTH_RANGE_S = (1e-9, 1e-3)
_N_CHANNELS = 4
_ERROR_QUEUE_LEN = 20


class _ScpiError(Exception):
    def __init__(self, code: int):
        self.code = code


def _keyword(token: str, long_form: str) -> bool:
    """SCPI keyword match: the short form (the upper-case part) or the whole long form."""
    token = token.upper()
    short = "".join(c for c in long_form if c.isupper() or c.isdigit())
    return token in (short, long_form.upper())


class SyncInstrument:
    """The SCPI instrument behind the USB interface (no USB here).

    Parameters
    ----------
    lab_state : LabState
        Updated on every change of period, channel-1 delay and output state.
    serial_number : str
        Reported in ``*IDN?``.
    camera_channel : int
        Channel that triggers the streak camera: its delay is ``LabState.sync_delay_ps``
        and the camera sees light only while it and the system output are on.
    """

    def __init__(self, lab_state: LabState, serial_number: str, firmware: str = "1.0",
                 camera_channel: int = 1):
        if not 1 <= int(camera_channel) <= _N_CHANNELS:
            raise ValueError(f"camera_channel must be 1..{_N_CHANNELS}, got {camera_channel!r}")
        self.camera_channel = int(camera_channel)
        self.lab_state = lab_state
        self.serial_number = serial_number
        self.firmware = firmware
        self.errors: list[int] = []
        self.esr = 0
        self.reset()

    def reset(self) -> None:
        self.period_s = 12.5e-9
        self.output = False
        self.delay_s = [0.0] * (_N_CHANNELS + 1)
        self.width_s = [10e-9] * (_N_CHANNELS + 1)
        self.channel_on = [True] * (_N_CHANNELS + 1)
        self._publish()

    def _publish(self) -> None:
        with self.lab_state.lock:
            self.lab_state.sync_rate_hz = 1.0 / self.period_s
            ch = self.camera_channel
            self.lab_state.sync_delay_ps = round(self.delay_s[ch] * 1e13) / 10.0
            self.lab_state.sync_output_enabled = bool(self.output and self.channel_on[ch])

    def push_error(self, code: int) -> None:
        if len(self.errors) >= _ERROR_QUEUE_LEN:
            self.errors[-1] = -350
        else:
            self.errors.append(int(code))
        # IEEE 488.2 event status register bits: 2 query, 3 device-dependent, 4 execution, 5 command
        if -199 <= code <= -100:
            self.esr |= 0x20
        elif -299 <= code <= -200:
            self.esr |= 0x10
        elif -399 <= code <= -300 or code > 0:
            self.esr |= 0x08
        elif -499 <= code <= -400:
            self.esr |= 0x04

    def status_byte(self, message_available: bool) -> int:
        stb = 0
        if self.errors:
            stb |= 0x04          # error/event queue not empty
        if message_available:
            stb |= 0x10          # MAV
        if self.esr:
            stb |= 0x20          # ESB (all ESR bits enabled)
        return stb

    @staticmethod
    def headers(message: str) -> list[str]:
        """SCPI headers of a program message (for fault matching), leading colon removed."""
        out = []
        for unit in message.split(";"):
            unit = unit.strip()
            if unit:
                out.append(unit.split(None, 1)[0].lstrip(":"))
        return out

    def execute(self, message: str, message_available: bool = False) -> list[str]:
        """Run one program message (units separated by ``;``); return the query responses."""
        responses = []
        for unit in message.split(";"):
            unit = unit.strip()
            if not unit:
                continue
            try:
                reply = self._unit(unit, message_available)
            except _ScpiError as exc:
                self.push_error(exc.code)
                continue
            if reply is not None:
                responses.append(reply)
        return responses

    # -- one program message unit
    def _unit(self, unit: str, message_available: bool):
        parts = unit.split(None, 1)
        header, arg = parts[0], (parts[1].strip() if len(parts) > 1 else None)
        query = header.endswith("?")
        if query and arg is not None:
            raise _ScpiError(-108)
        head = header[:-1] if query else header
        if head.startswith("*"):
            return self._common(head.upper(), query, arg, message_available)
        nodes = head.lstrip(":").split(":")
        if len(nodes) >= 2 and _keyword(nodes[0], "SYSTem") and _keyword(nodes[1], "ERRor") and \
                (len(nodes) == 2 or (len(nodes) == 3 and _keyword(nodes[2], "NEXT"))):
            if not query:
                raise _ScpiError(-113)
            code = self.errors.pop(0) if self.errors else 0
            return f'{code},"{SCPI_ERRORS.get(code, "Device-specific error")}"'
        if len(nodes) == 2 and nodes[0].upper().startswith("PULS"):
            return self._pulse(nodes[0], nodes[1], query, arg)
        raise _ScpiError(-113)

    def _common(self, head: str, query: bool, arg, message_available: bool):
        if arg is not None:
            raise _ScpiError(-108)
        if head == "*IDN" and query:
            return f"STREAKLAB,SLS-575SIM,{self.serial_number},{self.firmware}"
        if head == "*RST" and not query:
            self.reset()
            return None
        if head == "*CLS" and not query:
            self.errors.clear()
            self.esr = 0
            return None
        if head == "*OPC":
            if query:
                return "1"
            self.esr |= 0x01
            return None
        if head == "*WAI" and not query:
            return None
        if head == "*ESR" and query:
            value, self.esr = self.esr, 0
            return str(value)
        if head == "*STB" and query:
            return str(self.status_byte(message_available))
        if head == "*TST" and query:
            return "0"
        raise _ScpiError(-113)

    def _pulse(self, node: str, leaf: str, query: bool, arg):
        upper = node.upper()
        digits = upper[len("PULSE"):] if upper.startswith("PULSE") else upper[len("PULS"):]
        if not digits.isdigit():
            raise _ScpiError(-113)
        ch = int(digits)
        if ch > _N_CHANNELS:
            raise _ScpiError(-113)
        if _keyword(leaf, "STATe"):
            if query:
                return "1" if (self.output if ch == 0 else self.channel_on[ch]) else "0"
            value = self._boolean(arg)
            if ch == 0:
                self.output = value
            else:
                self.channel_on[ch] = value
        elif ch == 0 and _keyword(leaf, "PERiod"):
            if query:
                return f"{self.period_s:.12E}"
            self.period_s = self._number(arg, _PERIOD_RANGE_S)
        elif ch > 0 and _keyword(leaf, "DELay"):
            if query:
                return f"{self.delay_s[ch]:.13E}"
            value = self._number(arg, _DELAY_RANGE_S)
            self.delay_s[ch] = round(value * 1e13) / 1e13   # 0.1 ps resolution
        elif ch > 0 and _keyword(leaf, "WIDTh"):
            if query:
                return f"{self.width_s[ch]:.13E}"
            self.width_s[ch] = round(self._number(arg, _WIDTH_RANGE_S) * 1e13) / 1e13
        else:
            raise _ScpiError(-113)
        self._publish()
        return None

    @staticmethod
    def _boolean(arg) -> bool:
        if arg is None:
            raise _ScpiError(-109)
        text = arg.upper()
        if text in ("ON", "1"):
            return True
        if text in ("OFF", "0"):
            return False
        raise _ScpiError(-224)

    @staticmethod
    def _number(arg, bounds) -> float:
        if arg is None:
            raise _ScpiError(-109)
        try:
            value = float(arg)
        except ValueError:
            raise _ScpiError(-104) from None
        if not math.isfinite(value) or not bounds[0] <= value <= bounds[1]:
            raise _ScpiError(-222)
        return value


# ---------------------------------------------------------------- descriptors
def _ns(**fields) -> SimpleNamespace:
    return SimpleNamespace(**fields)


class _DeviceId:
    """What ``enumerate_devices`` yields: one plug-in of the device (a re-plug is a new one)."""

    def __init__(self, bus: int, address: int, generation: int):
        self.bus, self.address, self.generation = bus, address, generation

    def __repr__(self):
        return f"<simulated USBTMC device bus {self.bus} address {self.address}>"


class _Handle:
    def __init__(self, dev: _DeviceId):
        self.dev = dev
        self.claimed: set[int] = set()
        self.open = True


class UsbtmcBackend(usb.backend.IBackend):
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
                 log_length: int = 10000, camera_channel: int = 1):
        super().__init__()
        self.lab_state = lab_state if lab_state is not None else LabState()
        self.vendor_id, self.product_id = int(vendor_id), int(product_id)
        self.serial_number = serial_number
        self.strings = {1: manufacturer, 2: product, 3: serial_number}
        self.instrument = SyncInstrument(self.lab_state, serial_number, camera_channel=camera_channel)
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

    # ------------------------------------------------------------ descriptors
    def _device_descriptor(self):
        return _ns(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0,
                   bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64,
                   idVendor=self.vendor_id, idProduct=self.product_id, bcdDevice=0x0100,
                   iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
                   address=self._dev.address, bus=self._dev.bus, port_number=1,
                   port_numbers=(1,), speed=2)  # libusb LIBUSB_SPEED_FULL

    @staticmethod
    def _interface_descriptor():
        return _ns(bLength=9, bDescriptorType=4, bInterfaceNumber=INTERFACE_NUMBER,
                   bAlternateSetting=0, bNumEndpoints=3, bInterfaceClass=0xFE,
                   bInterfaceSubClass=0x03, bInterfaceProtocol=0x01, iInterface=0,
                   extra_descriptors=[])

    @staticmethod
    def _endpoint_descriptors():
        return [
            _ns(bLength=7, bDescriptorType=5, bEndpointAddress=EP_BULK_OUT, bmAttributes=0x02,
                wMaxPacketSize=MAX_PACKET, bInterval=0, bRefresh=0, bSynchAddress=0,
                extra_descriptors=[]),
            _ns(bLength=7, bDescriptorType=5, bEndpointAddress=EP_BULK_IN, bmAttributes=0x02,
                wMaxPacketSize=MAX_PACKET, bInterval=0, bRefresh=0, bSynchAddress=0,
                extra_descriptors=[]),
            _ns(bLength=7, bDescriptorType=5, bEndpointAddress=EP_INTR_IN, bmAttributes=0x03,
                wMaxPacketSize=2, bInterval=10, bRefresh=0, bSynchAddress=0,
                extra_descriptors=[]),
        ]

    def _configuration_descriptor(self):
        total = 9 + 9 + 7 * 3
        return _ns(bLength=9, bDescriptorType=2, wTotalLength=total, bNumInterfaces=1,
                   bConfigurationValue=CONFIG_VALUE, iConfiguration=0, bmAttributes=0x80,
                   bMaxPower=50, extra_descriptors=[])

    def _descriptor_bytes(self, dtype: int, index: int, langid: int) -> bytes:
        if dtype == 1 and index == 0:
            d = self._device_descriptor()
            return struct.pack("<BBHBBBBHHHBBBB", 18, 1, d.bcdUSB, d.bDeviceClass, d.bDeviceSubClass,
                               d.bDeviceProtocol, d.bMaxPacketSize0, d.idVendor, d.idProduct,
                               d.bcdDevice, 1, 2, 3, 1)
        if dtype == 2 and index == 0:
            c, i = self._configuration_descriptor(), self._interface_descriptor()
            out = struct.pack("<BBHBBBBB", 9, 2, c.wTotalLength, 1, CONFIG_VALUE, 0, 0x80, 50)
            out += struct.pack("<BBBBBBBBB", 9, 4, i.bInterfaceNumber, 0, i.bNumEndpoints,
                               0xFE, 0x03, 0x01, 0)
            for e in self._endpoint_descriptors():
                out += struct.pack("<BBBBHB", 7, 5, e.bEndpointAddress, e.bmAttributes,
                                   e.wMaxPacketSize, e.bInterval)
            return out
        if dtype == 3:
            if index == 0:
                return bytes([4, 3]) + struct.pack("<H", 0x0409)  # LANGID US English
            if index in self.strings and langid == 0x0409:
                text = self.strings[index].encode("utf-16-le")
                return bytes([2 + len(text), 3]) + text
        raise _usb_error("pipe")  # unknown descriptor: the device STALLs the request

    # ------------------------------------------------------------ IBackend: enumeration
    def enumerate_devices(self):
        with self._cv:
            return [self._dev] if self._plugged else []

    def get_parent(self, dev):
        return None

    def get_device_descriptor(self, dev):
        self._check_dev(dev)
        return self._device_descriptor()

    def get_configuration_descriptor(self, dev, config):
        self._check_dev(dev)
        if config != 0:
            raise IndexError("configuration index out of range")
        return self._configuration_descriptor()

    def get_interface_descriptor(self, dev, intf, alt, config):
        self._check_dev(dev)
        if (config, intf, alt) != (0, 0, 0):
            raise IndexError("interface/alternate setting index out of range")
        return self._interface_descriptor()

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        self._check_dev(dev)
        eps = self._endpoint_descriptors()
        if (config, intf, alt) != (0, 0, 0) or not 0 <= ep < len(eps):
            raise IndexError("endpoint index out of range")
        return eps[ep]

    def _check_dev(self, dev) -> None:
        if not isinstance(dev, _DeviceId):
            raise _usb_error("invalid")

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
