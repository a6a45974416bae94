"""Connection limits of ``driftlab serve``: a request's head and body must arrive in time, idle ones are closed.

uvicorn closes an idle keep-alive connection after ``timeout_keep_alive`` seconds, but restarts that
clock on every byte received and sets no clock at all on a fresh connection (``H11Protocol``: the
keep-alive timer is armed only after a response, and ``data_received`` cancels it). A client that
opens a connection and sends nothing, or trickles a header a byte at a time (slowloris), holds a
connection and a file descriptor for ever: 1,000 of 1,000 such connections were still open after
65 s (issue 36).

``GuardedH11Protocol`` adds two deadlines that bytes do not reset, following h11's view of the client
(``Connection.their_state``, h11 0.16): while the client owes a request head (``IDLE``: a new
connection, or a kept-alive one after its response) the whole head must arrive within
``header_timeout_s``; once the head is in, the body (``SEND_BODY``) within ``body_timeout_s``. Past a
deadline the connection is closed, with ``408 Request Timeout`` (RFC 9110 section 15.5.9) when part
of a request had arrived. While the application works and answers (the client is ``DONE``; the live
page's event stream) no deadline runs.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

#: the answer to a request that did not arrive in time (sent only when part of one had)
REQUEST_TIMEOUT = b"HTTP/1.1 408 Request Timeout\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"


@dataclass(frozen=True)
class ConnectionLimits:
    """How long a client may take over a request's head and its body, and stay idle between requests (s)."""

    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    keep_alive_s: int = 5


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with head and body deadlines that trickled bytes do not reset."""

    limits = ConnectionLimits()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._phase: object = None  # the h11 state of the client the running deadline is for
        self._received = False  # some bytes of the request awaited have arrived

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        """Accept the connection and start the clock of its first request head."""
        super().connection_made(transport)
        self._follow()

    def data_received(self, data: bytes) -> None:
        """Feed the bytes to h11, then move the deadline if the client moved on (head in, body in)."""
        self._received = True
        super().data_received(data)
        self._follow()

    def on_response_complete(self) -> None:
        """After a response the next request's head (or a pipelined one's body) has its own deadline."""
        super().on_response_complete()
        self._follow()

    def connection_lost(self, exc: Exception | None) -> None:
        """Drop the deadline with the connection."""
        self._cancel()
        super().connection_lost(exc)

    def _follow(self) -> None:
        """Arm the deadline of the client's current state (head or body), or none while the server works."""
        if self.transport is None or self.transport.is_closing():
            self._cancel()
            return
        state = self.conn.their_state
        if state is self._phase:
            return
        self._cancel()
        self._phase = state
        if state is h11.IDLE:
            self._received = False
            timeout = self.limits.header_timeout_s
        elif state is h11.SEND_BODY:
            timeout = self.limits.body_timeout_s
        else:
            return
        self._deadline = self.loop.call_later(timeout, self._expire)

    def _cancel(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self._phase = None

    def _expire(self) -> None:
        """Close a connection whose request head or body did not arrive in time (408 if it had begun)."""
        self._deadline = None
        if self.transport.is_closing():
            return
        # a head begun and no response under way: say why (a body's deadline closes without a word,
        # the application holds that request's cycle)
        head_begun = self.conn.their_state is h11.IDLE and self._received
        if head_begun and (self.cycle is None or self.cycle.response_complete):
            self.transport.write(REQUEST_TIMEOUT)
        self.transport.close()


def server_config(app: Any, host: str, port: int, log_level: str, limits: ConnectionLimits) -> uvicorn.Config:
    """Return uvicorn's configuration of ``driftlab serve``: one worker, the guarded h11 protocol, ``limits``."""
    protocol = type("GuardedH11", (GuardedH11Protocol,), {"limits": limits})
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        log_level=log_level,
        workers=1,
        access_log=False,
        http=protocol,
        timeout_keep_alive=limits.keep_alive_s,
    )
