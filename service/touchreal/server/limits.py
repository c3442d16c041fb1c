"""Connection limits of the HTTP server (uvicorn): the keyword arguments from the settings; the
request-head timeout uvicorn lacks (it only times out idle keep-alive connections, so a client that
opens connections and never finishes its headers would hold their descriptors forever); a bounded
kernel send buffer per connection (with Linux's autotuning a slow WebSocket reader's frames wait
seconds in the kernel, where the hub's frame age limit cannot drop them); and which peers'
``X-Forwarded-For`` is believed (none by default, so a client cannot choose the address its failed
logins are counted under)."""

from __future__ import annotations

import asyncio
import socket
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from .settings import ServerSettings


class HeadTimeoutH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, plus: a connection whose request head is not complete
    :attr:`head_timeout_s` after it connected (or after its last response) is closed."""

    head_timeout_s: float = 10.0
    send_buffer_bytes: int = 0  #: SO_SNDBUF of each connection (0: leave the kernel's autotuning)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        sock = transport.get_extra_info("socket")
        if self.send_buffer_bytes and sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer_bytes)
        super().connection_made(transport)
        self._head_timer: asyncio.TimerHandle | None = None
        self._arm_head_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_timed_out)

    def _head_timed_out(self) -> None:
        self._head_timer = None
        waiting = self.conn.their_state is h11.IDLE  # no complete request head since (re)arming
        if waiting and self.transport.get_protocol() is self and not self.transport.is_closing():
            self.transport.close()


def uvicorn_limits(settings: ServerSettings) -> dict[str, Any]:
    """uvicorn.Config keyword arguments for the settings' connection limits."""
    protocol = type("HeadTimeoutH11Protocol", (HeadTimeoutH11Protocol,), {"head_timeout_s": settings.header_timeout_s,
                                                                          "send_buffer_bytes": settings.send_buffer_bytes})
    proxies = list(settings.forwarded_allow_ips)
    return {"http": protocol, "timeout_keep_alive": settings.keep_alive_s,
            "h11_max_incomplete_event_size": settings.max_header_bytes, "limit_concurrency": settings.limit_concurrency,
            "proxy_headers": bool(proxies), "forwarded_allow_ips": proxies or None}
