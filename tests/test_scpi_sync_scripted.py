"""The SCPI laser-sync command table, byte for byte, over an in-memory ScriptedTransport."""
from __future__ import annotations

import pytest

from drivers.errors import DeviceError, DeviceTimeout, ProtocolError
from drivers.interfaces import LaserSync
from drivers.scpi_sync import COMMANDS, ScpiLaserSync, program_message
from drivers.transport import ScriptedTransport

OK = b'0,"No error"\n'


def scripted(script, **kwargs):
    t = ScriptedTransport(script, terminator=b"\n", timeout_s=0.3)
    return t, ScpiLaserSync(transport=t, **kwargs)


def test_table_messages():
    assert program_message("period", 1.25e-08) == ":PULS0:PER 1.25e-08"
    assert program_message("delay", 1.2345e-09, channel=3) == ":PULS3:DEL 1.2345e-09"
    assert program_message("delay", channel=2, query=True) == ":PULS2:DEL?"
    assert program_message("output", True) == ":PULS0:STAT ON"
    assert program_message("identify", query=True) == "*IDN?"
    assert program_message("reset") == "*RST"
    with pytest.raises(ValueError, match="cannot be set"):
        program_message("identify")
    with pytest.raises(ValueError, match="cannot be queried"):
        program_message("reset", query=True)
    assert all(c.header.startswith(("*", ":", "SYST")) for c in COMMANDS.values())


def test_settings_and_their_error_checks_on_the_wire():
    t, sync = scripted([
        (b":PULS0:PER 1.25e-08\n", None), (b"SYST:ERR?\n", OK),
        (b":PULS1:DEL 1.2345e-09\n", None), (b"SYST:ERR?\n", OK),
        (b":PULS2:DEL 5e-11\n", None), (b"SYST:ERR?\n", OK),
        (b":PULS0:STAT ON\n", None), (b"SYST:ERR?\n", OK),
        (b":PULS0:PER?\n", b"1.250000000000E-08\n"),
        (b":PULS1:DEL?\n", b"1.2345000000000E-09\n"),
        (b":PULS0:STAT?\n", b"1\n"),
    ])
    assert isinstance(sync, LaserSync)
    sync.set_repetition_rate(80e6)
    sync.set_trigger_delay(1234.5)
    sync.set_trigger_delay(50.0, channel=2)
    sync.set_output(True)
    assert sync.repetition_rate() == pytest.approx(80e6)
    assert sync.trigger_delay() == 1234.5
    assert sync.output_enabled() is True
    t.assert_done()


def test_queued_errors_become_one_device_error_naming_all():
    t, sync = scripted([
        (b":PULS0:PER 1e-09\n", None),
        (b"SYST:ERR?\n", b'-222,"Data out of range"\n'),
        (b"SYST:ERR?\n", b'-410,"Query INTERRUPTED"\n'),
        (b"SYST:ERR?\n", OK),
    ])
    with pytest.raises(DeviceError, match=r"Data out of range \(\+1 more") as info:
        sync.set_repetition_rate(1e9)
    assert (info.value.code, info.value.command) == (-222, ":PULS0:PER 1e-09")
    t.assert_done()


def test_identify_reset_and_malformed_replies():
    t, sync = scripted([
        (b"*IDN?\n", b"ACME,DG,1,2\n"),
        (b"*RST\n", None), (b"*OPC?\n", b"1\n"),
        (b"*IDN?\n", b"no commas\n"),
        (b"SYST:ERR?\n", b"garbled\n"),
        (b":PULS0:STAT?\n", b"1"),          # no newline before the timeout
    ])
    assert sync.identify() == "ACME,DG,1,2"
    sync.reset()
    with pytest.raises(ProtocolError, match="four comma-separated"):
        sync.identify()
    with pytest.raises(ProtocolError, match="malformed SYST:ERR"):
        sync.read_errors()
    with pytest.raises(DeviceTimeout, match="no complete line"):
        sync.output_enabled()


def test_leaving_the_block_switches_the_output_off():
    t, sync = scripted([(b":PULS0:STAT OFF\n", None), (b"SYST:ERR?\n", OK)])
    with pytest.raises(RuntimeError):
        with sync:
            raise RuntimeError("scan aborted")
    t.assert_done()
    assert t.closed
