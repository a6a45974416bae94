"""The virtual controller's DNC port: a control reading a drip-fed tape from a TCP serial server, in real time.

``SimDncControl`` listens on 127.0.0.1 (``socket://127.0.0.1:PORT``, as a TCP serial server would
offer the control's RS-232 port) and reads a tape framed as a ``daq.dnc.Profile`` says (leader,
``%``, blocks ended by the profile's end of block, ``%``; or the TNC's NUL NUL ... ETX). It holds at
most ``buffer_bytes`` received bytes, executes one block every ``block_s``, sends DC3 when fewer
than ``dc3_free`` bytes are free and DC1 once fewer than ``dc1_fill`` are held (the handshake of
daq.dnc's manuals), starts the transfer with DC1 when the profile's control does (every 0.5 s until the
tape comes), and pauses for
``hold(seconds)`` (a feed hold: its buffer fills and DC3 holds the sender). A byte arriving when the
buffer is full is lost and counted (``overflow``); a byte with the 8th bit set is a parity error.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from typing import Self

from driftlab.daq.dnc import DC1, DC2, DC3, DC4, EOT, NUL, Profile


class SimDncControl:
    """A control on a DNC line (module docstring); ``blocks`` are the ones it executed, in order."""

    def __init__(
        self,
        prof: Profile,
        buffer_bytes: int = 1024,
        block_s: float = 0.005,
        dc3_free: int = 256,
        dc1_fill: int = 512,
    ) -> None:
        self.profile = prof
        self.buffer_bytes, self.block_s = buffer_bytes, block_s
        self.dc3_free, self.dc1_fill = dc3_free, dc1_fill
        self.blocks: list[str] = []
        self.overflow = self.parity_errors = self.max_held = self.dc3_sent = 0
        self.done = threading.Event()
        self._queue: deque[bytes] = deque()
        self._held = 0
        self._line = bytearray()
        self._in_record = False
        self._ended = False
        self._xoff = False
        self._hold_until = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(1)
        self._listener.settimeout(0.05)
        self._thread = threading.Thread(target=self._run, name="sim-dnc", daemon=True)

    @property
    def url(self) -> str:
        """Return the pyserial URL of the control's port."""
        return f"socket://127.0.0.1:{self._listener.getsockname()[1]}"

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def hold(self, seconds: float) -> None:
        """Stop executing blocks for ``seconds`` from now (a feed hold)."""
        with self._lock:
            self._hold_until = time.monotonic() + seconds

    def close(self) -> None:
        """Stop the control."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._listener.close()

    # -- the line
    def _run(self) -> None:
        conn = None
        while not self._stop.is_set() and conn is None:
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
        if conn is None:
            return
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(min(self.block_s, 0.01))
            next_exec = time.monotonic()
            started = not self.profile.wait_dc1
            closed = False
            asked = -1.0
            while not self._stop.is_set():
                out = bytearray()
                if not started and time.monotonic() - asked > 0.5:
                    # the operator starts the input (again, until the tape comes: a DC1 sent before the
                    # sender had opened its end, or that its open flushed, is lost as on a real line)
                    out.append(DC1)
                    asked = time.monotonic()
                data = b""
                if not closed:
                    try:
                        data = conn.recv(4096)
                        closed = not data  # the sender is done: what the buffer holds still runs
                    except TimeoutError:
                        pass
                    except OSError:
                        closed = True
                elif self._queue:
                    time.sleep(max(min(next_exec - time.monotonic(), 0.01), 0.0))
                else:
                    break
                started = started or bool(data)
                for b in data:
                    self._receive(b, out)
                now = time.monotonic()
                with self._lock:
                    held_up = now < self._hold_until
                while not held_up and self._queue and now >= next_exec:
                    self._execute(out)
                    next_exec = max(next_exec + self.block_s, now - self.block_s)
                if not self._queue:
                    next_exec = max(next_exec, now)
                if out and not closed:
                    try:
                        conn.sendall(bytes(out))
                    except OSError:
                        closed = True

    def _receive(self, b: int, out: bytearray) -> None:
        """Take one byte off the line."""
        prof = self.profile
        if b & 0x80:
            self.parity_errors += 1
            return
        if self._ended:
            return
        if not self._in_record:
            if b in (NUL, DC2, DC4):
                return
            if prof.record_marks and b != ord("%"):
                return
            self._in_record = True
            if prof.record_marks:
                self._line = bytearray(b"%")
                return
        if not prof.record_marks and prof.trailer and b == prof.trailer[0]:
            self._ended = True
            out.append(EOT)
            return
        if self._held >= self.buffer_bytes:
            self.overflow += 1
            return
        self._line.append(b)
        self._held += 1
        self.max_held = max(self.max_held, self._held)
        if self.buffer_bytes - self._held < self.dc3_free and not self._xoff:
            self._xoff = True
            self.dc3_sent += 1
            out.append(DC3)
        if self._line.endswith(prof.eob):
            text = bytes(self._line[: -len(prof.eob)])
            self._line = bytearray()
            if text == b"%":
                if self.blocks or self._queue:
                    self._ended = True
                    self._queue.append(b"%")
                else:  # the opening mark's end of block
                    self._held -= len(prof.eob)
                return
            self._queue.append(text)

    def _execute(self, out: bytearray) -> None:
        """Run the next block of the buffer."""
        text = self._queue.popleft()
        if text == b"%":
            self.done.set()
            return
        self._held -= len(text) + len(self.profile.eob)
        self.blocks.append(text.decode("ascii"))
        if self._ended and not self._queue:
            self.done.set()
        if self._xoff and self._held < self.dc1_fill:
            self._xoff = False
            out.append(DC1)
