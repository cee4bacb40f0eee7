"""The simulated USB device as enumeration sees it: constants, descriptors, libusb-style errors.

:class:`UsbDescriptors` is the part of :class:`~drivers.sim.usbtmc.UsbtmcBackend`
that answers pyusb's enumeration calls (``enumerate_devices``,
``get_*_descriptor``) and GET_DESCRIPTOR: one full-speed device, one
configuration, one USBTMC/USB488 interface (class 0xFE, subclass 0x03,
protocol 0x01) with Bulk-OUT, Bulk-IN and Interrupt-IN endpoints, and string
descriptors (USB 2.0 specification, chapter 9; USBTMC 1.0 section 4.2).
"""
from __future__ import annotations

import errno
import struct
from types import SimpleNamespace

from usb.core import USBError, USBTimeoutError

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

# The USBTMC 1.0 / USB488 numbers (MsgID values, class request codes, USBTMC_status
# values) have one home, the host driver: the device answers with the same table.
from drivers.usbtmc import (  # noqa: E402,F401
    CHECK_ABORT_BULK_IN_STATUS, CHECK_ABORT_BULK_OUT_STATUS, CHECK_CLEAR_STATUS, DEV_DEP_MSG_IN,
    DEV_DEP_MSG_OUT, GET_CAPABILITIES, INITIATE_ABORT_BULK_IN, INITIATE_ABORT_BULK_OUT, INITIATE_CLEAR,
    READ_STATUS_BYTE, REQUEST_DEV_DEP_MSG_IN, STATUS_FAILED, STATUS_PENDING, STATUS_SUCCESS,
    STATUS_TRANSFER_NOT_IN_PROGRESS,
)


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


class UsbDescriptors:
    """Descriptor and enumeration calls of the backend (mixed into ``UsbtmcBackend``).

    Uses the backend's ``vendor_id``, ``product_id``, ``strings``, ``_dev``,
    ``_plugged`` and ``_cv``.
    """

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
