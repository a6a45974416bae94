"""Transports: serial lines through pyserial's public API only; the VISA backend chosen by DRIFTLAB_VISA_LIBRARY."""

from __future__ import annotations

import ast
import socket
import threading
import time
from pathlib import Path

import pytest

from driftlab.daq.retry import TransportTimeout
from driftlab.daq.thermocouple import ThermocoupleCard, emf_mv
from driftlab.daq.transport import SerialPort, VisaPort, visa_library_spec, visa_resource_manager
from driftlab.errors import InstrumentError, ValidationError

TRANSPORT = Path(__file__).resolve().parents[2] / "driftlab" / "daq" / "transport.py"


def test_serial_port_uses_no_private_pyserial_attribute():
    """No ``obj._name`` on the serial object, and no getattr of a private name, anywhere in the transport."""
    tree = ast.parse(TRANSPORT.read_text())
    offenders = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            # self._x (our own state) is fine; self._ser._x or ser._x (pyserial's) is not
            if not (isinstance(base, ast.Name) and base.id in ("self", "cls")):
                offenders.append(f"line {node.lineno}: .{node.attr}")
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "getattr":
            args = node.args
            if len(args) >= 2 and isinstance(args[1], ast.Constant) and str(args[1].value).startswith("_"):
                offenders.append(f"line {node.lineno}: getattr {args[1].value}")
    assert offenders == []


class _Server:
    """A local TCP peer that sends scripted byte chunks with pauses, then optionally closes.

    It waits for one byte from the client first (``_open`` sends it once the port is open): pyserial's
    ``socket://`` open drops whatever input has already arrived (``reset_input_buffer``), so bytes sent
    at the accept could be lost on a loaded host before the test reads them.
    """

    def __init__(self, chunks: list[tuple[float, bytes]], close: bool = False) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.chunks = chunks
        self.close = close
        self.sent = threading.Event()  # every chunk handed to the socket
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        conn, _ = self.sock.accept()
        conn.recv(1)  # the client's port is open
        for pause, data in self.chunks:
            time.sleep(pause)
            conn.sendall(data)
        self.sent.set()
        if self.close:
            conn.close()
        else:
            time.sleep(5.0)  # open well past any read's timeout here
            conn.close()


def _open(server: _Server) -> SerialPort:
    """Return a port on ``server`` that has told the server it is open (see ``_Server``)."""
    port = SerialPort.open(f"socket://127.0.0.1:{server.port}", timeout_s=1.0)
    port.write(b"?")
    return port


def test_serial_lines_arrive_whole_from_pieces_and_batches():
    server = _Server([(0.0, b"ab"), (0.05, b"c\nde"), (0.05, b"f\ng\nh"), (0.0, b"\n")])
    port = _open(server)
    try:
        assert [port.read_line() for _ in range(4)] == [b"abc\n", b"def\n", b"g\n", b"h\n"]
        assert port._ser.timeout == 1.0  # the port's own timeout is restored after each line
    finally:
        port.close()


def test_serial_timeout_names_the_partial_line_and_a_closed_peer_is_reported():
    server = _Server([(0.0, b"12.5,")])
    # a second to wait for the rest: on a loaded host the loopback may hand over the sent bytes late
    port = _open(server)
    assert server.sent.wait(10.0)  # the partial line is sent before the wait starts, however loaded the host
    with pytest.raises(TransportTimeout, match=r"timeout waiting for reply \(partial b'12.5,'\)"):
        port.read_line()
    port.close()
    server = _Server([(0.0, b"x")], close=True)
    port = _open(server)
    with pytest.raises(TransportTimeout, match="connection closed by the instrument"):
        port.read_line()
    port.close()


def test_serial_loop_url_echoes_lines():
    port = SerialPort.open("loop://", timeout_s=0.5)
    port.write(b"PING\nPONG\n")
    assert port.read_line() == b"PING\n" and port.read_line() == b"PONG\n"
    with pytest.raises(TransportTimeout):
        port.read_line()
    port.close()


SIM_CARD = """spec: "1.1"
devices:
  card:
    eom:
      GPIB INSTR:
        q: "\\n"
        r: "\\n"
    dialogues:
      - q: "CJC?"
        r: "24.125"
      - q: "SCAN? 0,1"
        r: "{volts},9.9E37"
resources:
  GPIB0::9::INSTR:
    device: card
"""


def test_visa_backend_from_the_environment_reaches_a_simulated_card(tmp_path, monkeypatch):
    volts = (float(emf_mv("K", 60.0)) - float(emf_mv("K", 24.125))) * 1e-3
    defs = tmp_path / "card.yaml"
    defs.write_text(SIM_CARD.format(volts=f"{volts:.9e}"))
    monkeypatch.setenv("DRIFTLAB_VISA_LIBRARY", f"{defs}@sim")
    card = ThermocoupleCard.open("GPIB0::9::INSTR", {0: "T1", 1: "T2"}, tc_type="K")
    try:
        scan = card.scan()
    finally:
        card.close()
    assert scan.values["T1"] == pytest.approx(60.0, abs=1e-5)
    assert scan.flags == {"T2": "open_thermocouple"}


@pytest.mark.parametrize(
    "spec,needle",
    [
        ("@nope", "use @py, @sim, FILE.yaml@sim, @ivi"),
        ("/no/such/libvisa.so", r"no such file \(give the path of the vendor.s VISA library\)"),
        ("/no/such/defs.yaml@sim", "no such pyvisa-sim definitions file"),
    ],
)
def test_bad_visa_library_settings_are_one_line_errors(spec, needle, monkeypatch):
    monkeypatch.setenv("DRIFTLAB_VISA_LIBRARY", spec)
    with pytest.raises(ValidationError, match=needle):
        VisaPort.open("GPIB0::9::INSTR")


def test_visa_library_default_and_a_vendor_library_that_does_not_load(tmp_path, monkeypatch):
    monkeypatch.delenv("DRIFTLAB_VISA_LIBRARY", raising=False)
    assert visa_library_spec() == "@py"
    fake = tmp_path / "libvisa.so"
    fake.write_bytes(b"not a shared library")
    with pytest.raises(InstrumentError, match="cannot load VISA library"):
        visa_resource_manager(str(fake))


def test_a_visa_socket_session_sends_a_query_right_after_a_command():
    """A command then a query on a TCPIP SOCKET session: the query leaves at once (Nagle off, as VISA's default).

    With Nagle's algorithm on, the query waits for the ACK of the command, which a listener with
    nothing to answer delays; the test looks at the socket option itself, not at a time.
    """
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    rm = visa_resource_manager("@py")
    try:
        vp = VisaPort.open(f"TCPIP0::127.0.0.1::{port}::SOCKET", resource_manager=rm)
        session = rm.visalib.sessions[vp._res.session]
        assert session.interface.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) == 1
        vp.close()
    finally:
        rm.close()
        listener.close()
