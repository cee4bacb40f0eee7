"""drivers.transport: the scripted in-memory transport, and serial (pty, loop://) and TCP links."""
from __future__ import annotations

import os
import select
import socket
import termios
import threading
import time
import tty

import pytest

from drivers.errors import ConnectionLost, DeviceTimeout, ProtocolError
from drivers.transport import LineTransport, ScriptedTransport, SerialLineTransport, TcpLineTransport

pytestmark = pytest.mark.timeout(20)


# ---------------------------------------------------------------- ScriptedTransport
def test_scripted_exchanges_in_order_and_assert_done_passes():
    with ScriptedTransport([(b"1TP\r\n", b"1TP12.5\r\n"), (b"1ST\r\n", None),
                            (b"1ID?\r\n", b"1IDX\r\n")]) as t:
        assert isinstance(t, LineTransport)
        assert t.query(b"1TP\r\n") == b"1TP12.5\r\n"
        t.write(b"1ST\r\n")
        t.write(b"1ID?\r\n")
        assert t.read_line() == b"1IDX\r\n"
    assert t.written == [b"1TP\r\n", b"1ST\r\n", b"1ID?\r\n"] and t.closed


def test_a_write_that_differs_from_the_script_names_step_and_bytes():
    t = ScriptedTransport([(b"1TP\r\n", b"1TP0\r\n")])
    with pytest.raises(AssertionError, match=r"step 0: expected b'1TP\\r\\n', got b'1TS\\r\\n'"):
        t.write(b"1TS\r\n")
    with pytest.raises(AssertionError, match="step 0"):   # remembered even if a driver swallowed it
        t.assert_done()


def test_unexpected_extra_write_and_missing_steps_fail():
    t = ScriptedTransport([(b"a\r\n", None)])
    t.write(b"a\r\n")
    with pytest.raises(AssertionError, match="unexpected write"):
        t.write(b"b\r\n")
    t2 = ScriptedTransport([(b"a\r\n", None), (b"b\r\n", None)])
    t2.write(b"a\r\n")
    with pytest.raises(AssertionError, match=r"1 scripted step\(s\) never written, next expected b'b\\r\\n'"):
        t2.assert_done()
    with pytest.raises(AssertionError, match="never written"):
        with ScriptedTransport([(b"a\r\n", None)]):
            pass


def test_unread_reply_bytes_fail_assert_done():
    t = ScriptedTransport([(b"q\r\n", b"one\r\ntwo\r\n")])
    t.write(b"q\r\n")
    assert t.read_line() == b"one\r\n"
    with pytest.raises(AssertionError, match="left unread: b'two"):
        t.assert_done()


def test_missing_reply_is_an_immediate_timeout_and_the_next_write_drains():
    t = ScriptedTransport([(b"1TP\r\n", b"1TP12"), (b"1TS\r\n", b"1TS00000A\r\n")], timeout_s=5.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"got b'1TP12'"):
        t.query(b"1TP\r\n")
    assert time.monotonic() - t0 < 0.5          # nothing more can arrive: no waiting
    assert t.stale
    t.feed(b"5\r\n")                            # the late rest of the reply
    assert t.query(b"1TS\r\n") == b"1TS00000A\r\n"
    assert t.drained == [b"1TP125\r\n"]
    t.assert_done()


def test_line_without_full_terminator_and_overlong_line_are_protocol_errors():
    t = ScriptedTransport([(b"x\r\n", b"abc\n"), (b"y\r\n", b"z" * 40)], max_line=32)
    with pytest.raises(ProtocolError) as info:
        t.query(b"x\r\n")
    assert info.value.raw == b"abc\n"
    with pytest.raises(ProtocolError, match="longer than 32") as info:
        t.query(b"y\r\n")
    assert info.value.raw == b"z" * 40


def test_extra_bytes_after_a_query_reply_are_discarded_before_the_next_write():
    t = ScriptedTransport([(b"a\r\n", b"A\r\nnoise\r\n"), (b"b\r\n", b"B\r\n")])
    assert t.query(b"a\r\n") == b"A\r\n"
    assert t.stale
    assert t.query(b"b\r\n") == b"B\r\n"
    assert t.drained == [b"noise\r\n"]
    t.assert_done()


def test_broken_link_reconnects_once_and_repeats_the_exchange():
    t = ScriptedTransport([(b"1TP\r\n", ConnectionResetError("gone")), (b"1TP\r\n", b"1TP1\r\n")])
    assert t.query(b"1TP\r\n") == b"1TP1\r\n"
    assert t.reconnects == 1
    t.assert_done()
    t2 = ScriptedTransport([(b"x\r\n", OSError(5, "EIO")), (b"x\r\n", OSError(5, "EIO"))])
    with pytest.raises(ConnectionLost, match="connection lost"):
        t2.write(b"x\r\n")
    t3 = ScriptedTransport([(b"x\r\n", OSError(5, "EIO"))], reconnect_attempts=0)
    with pytest.raises(ConnectionLost):
        t3.write(b"x\r\n")
    assert t3.reconnects == 0


def test_read_exactly_and_lock_is_reentrant():
    t = ScriptedTransport([(b"IMG\r\n", b"OK 4\r\n\x00\x01\x02\x03")])
    with t.lock, t.lock:
        assert t.query(b"IMG\r\n") == b"OK 4\r\n"
    assert t.read_exactly(4) == b"\x00\x01\x02\x03"
    with pytest.raises(DeviceTimeout):
        t.read_exactly(1)


def test_closed_transport_and_bad_arguments():
    t = ScriptedTransport([])
    t.close()
    with pytest.raises(ConnectionLost, match="closed"):
        t.write(b"x")
    with pytest.raises(ValueError, match="pair"):
        ScriptedTransport([b"just bytes"])
    with pytest.raises(ValueError, match="timeout_s"):
        ScriptedTransport([], timeout_s=0)
    with pytest.raises(ValueError, match="zero bytes"):
        ScriptedTransport([]).write(b"")


# ---------------------------------------------------------------- serial, over a pty
@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def test_serial_transport_on_a_pty_reads_lines_and_blocks(pty_pair):
    master, path = pty_pair
    with SerialLineTransport(path, baudrate=57600, timeout_s=0.5) as t:
        t.write(b"1TP\r\n")
        assert os.read(master, 64) == b"1TP\r\n"
        os.write(master, b"1TP3.5\r\nrest")
        assert t.read_line() == b"1TP3.5\r\n"
        assert t.read_exactly(4) == b"rest"
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            t.read_line(timeout_s=0.1)
        assert 0.09 <= time.monotonic() - t0 < 1.0
        os.write(master, b"late\r\n")
        assert select.select([t.serial.fd], [], [], 2.0)[0]   # the late bytes reached the port
        assert t.drain() == b"late\r\n"


def test_serial_transport_applies_xonxoff_and_line_settings(pty_pair):
    master, path = pty_pair
    with SerialLineTransport(path, baudrate=57600, xonxoff=True) as t:
        ser = t.serial
        assert (ser.baudrate, ser.bytesize, ser.parity, ser.stopbits) == (57600, 8, "N", 1)
        assert ser.xonxoff and not ser.rtscts
        iflag = termios.tcgetattr(ser.fd)[0]
        assert iflag & termios.IXON and iflag & termios.IXOFF
    with SerialLineTransport(path, xonxoff=False) as t:
        assert not termios.tcgetattr(t.serial.fd)[0] & termios.IXON


def test_serial_transport_on_a_vanished_port_is_connection_lost(pty_pair):
    with pytest.raises(ConnectionLost, match="/dev/does-not-exist"):
        SerialLineTransport("/dev/does-not-exist")
    t = SerialLineTransport("loop://", timeout_s=0.2)
    assert t.query(b"echo\r\n") == b"echo\r\n"      # loop:// returns what was written
    t.close()


# ---------------------------------------------------------------- TCP
@pytest.fixture
def loopback_server():
    """A listening socket on a free loopback port -> (server, port); every accept gives up
    after 5 s (a client that never connects fails the test there, not at the suite's timeout)."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(5.0)
    try:
        yield server, server.getsockname()[1]
    finally:
        server.close()


def _accept(server):
    conn, _ = server.accept()
    conn.settimeout(5.0)              # every recv on the test's side of the link waits 5 s at most
    return conn


def _after_a_timed_out_query(server, port, command):
    """A client whose ``command`` query timed out (0.2 s; its reply never sent) -> (transport,
    the server's end of the link)."""
    t = TcpLineTransport("127.0.0.1", port, timeout_s=0.2)
    conn = _accept(server)
    with pytest.raises(DeviceTimeout):
        t.query(command)
    return t, conn


def _query_while_serving(t, command, serve):
    """``t.query(command)`` (2 s) while ``serve()``, the device's side, runs on its own thread
    -> the reply; the thread is joined (5 s at most) either way."""
    th = threading.Thread(target=serve)
    th.start()
    try:
        return t.query(command, timeout_s=2.0)
    finally:
        th.join(5)


def test_tcp_transport_lines_blocks_timeout_and_peer_close(loopback_server):
    server, port = loopback_server
    t = TcpLineTransport("127.0.0.1", port, timeout_s=0.5)
    conn = _accept(server)
    t.write(b"AppInfo()\r\n")
    assert conn.recv(64) == b"AppInfo()\r\n"
    conn.sendall(b"0,ok\r\n\x01\x02\x03")
    assert t.read_line() == b"0,ok\r\n"
    assert t.read_exactly(3) == b"\x01\x02\x03"
    with pytest.raises(DeviceTimeout):
        t.read_line(timeout_s=0.05)
    conn.close()
    with pytest.raises(ConnectionLost, match="closed"):
        t.read_line()
    t.reconnect()
    conn2 = _accept(server)
    conn2.sendall(b"again\r\n")
    assert t.read_line() == b"again\r\n"
    t.close()
    conn2.close()
    server.close()
    with pytest.raises(ConnectionLost, match="cannot open 127.0.0.1"):
        TcpLineTransport("127.0.0.1", port, connect_timeout_s=0.5)


def test_a_late_reply_caught_mid_line_is_discarded_whole_before_the_next_command(loopback_server):
    # The first part of a late reply has arrived when the next command goes out; its rest is
    # still on the wire.  The resynchronisation waits for the end of that line and drops it, so
    # the rest is not taken for the next command's reply.
    server, port = loopback_server
    t, conn = _after_a_timed_out_query(server, port, b"1ID?\r\n")
    assert conn.recv(64) == b"1ID?\r\n"
    conn.sendall(b"1ID SMC_")
    assert select.select([t.sock], [], [], 2.0)[0]       # the first part is at the client
    seen = []

    def rest_then_answer():
        time.sleep(0.05)                                  # the rest is later on the wire
        conn.sendall(b"sim\r\n")
        seen.append(conn.recv(64))
        conn.sendall(b"1TS000033\r\n")

    assert _query_while_serving(t, b"1TS\r\n", rest_then_answer) == b"1TS000033\r\n"
    assert seen == [b"1TS\r\n"]
    t.close()
    conn.close()


def test_tcp_transport_discards_a_late_reply_and_reconnects_a_query_after_the_peer_went(loopback_server):
    server, port = loopback_server
    t, conn = _after_a_timed_out_query(server, port, b"slow?\r\n")
    conn.sendall(b"late answer\r\n")
    assert conn.recv(64) == b"slow?\r\n"
    deadline = time.monotonic() + 2
    while not t.drain() and time.monotonic() < deadline:   # the late line is thrown away
        pass
    conn.close()                                           # the peer goes away
    result = []

    def serve_once():
        c = _accept(server)
        result.append(c.recv(64))
        c.sendall(b"fresh\r\n")
        c.close()

    assert _query_while_serving(t, b"again?\r\n", serve_once) == b"fresh\r\n"
    assert result == [b"again?\r\n"]
    t.close()
