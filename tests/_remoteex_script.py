"""In-memory RemoteEx link for byte-exact protocol tests: two ScriptedTransports, no socket, no thread.

``scripted_camera(script)`` gives a RemoteExCamera whose command port checks every
command against ``script`` — ``(sent, reply)`` or ``(sent, reply, data_port_bytes)``
steps, byte for byte, in order — and whose data port delivers ``data_port_bytes``
when the step's command is written.  Both greetings are waiting when it connects.
A reply that is not scripted is a timeout at once.
"""
from drivers.errors import ConnectionLost
from drivers.remoteex import COMMAND_BANNER, DATA_BANNER, RemoteExCamera
from drivers.transport import ScriptedTransport


class CommandScript(ScriptedTransport):
    """The command port: a ScriptedTransport that also feeds the data port at the scripted steps."""

    def __init__(self, script, data: ScriptedTransport, banner: bytes = COMMAND_BANNER):
        steps = [tuple(s) for s in script]
        self.payloads = [s[2] if len(s) > 2 else None for s in steps]
        self.data = data
        super().__init__([(s[0], s[1]) for s in steps], terminator=b"\r", max_line=1 << 16, reconnect_attempts=0)
        self.feed(banner)

    def _send(self, data: bytes) -> None:
        step = self._step_no
        super()._send(data)
        payload = self.payloads[step] if step < len(self.payloads) else None
        if payload:
            self.data.feed(payload)


def scripted_link(script, *, banner=COMMAND_BANNER, data_banner=DATA_BANNER):
    """``(open_transports, command_script, data_transport)`` for a RemoteExLink / RemoteExCamera."""
    data = ScriptedTransport([], terminator=b"\r", max_line=1 << 20, reconnect_attempts=0, name="data port")
    data.feed(data_banner)
    cmd = CommandScript(script, data, banner)
    opened = []

    def open_transports(connect_timeout_s):
        if opened:
            raise ConnectionLost("the scripted link cannot be reopened")
        opened.append(connect_timeout_s)
        return cmd, data

    return open_transports, cmd, data


def scripted_camera(script, **kw):
    """``(camera, command_script, data_transport)``; the camera is connected, AppStart not sent by default."""
    open_transports, cmd, data = scripted_link(script)
    kw.setdefault("start_app", False)
    kw.setdefault("timeout_s", 1.0)
    kw.setdefault("poll_interval_s", 0.0)
    cam = RemoteExCamera("127.0.0.1", 1001, open_transports=open_transports, **kw)
    return cam, cmd, data
