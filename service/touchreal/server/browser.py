"""Browser security headers on every HTTP response of the service and the gateway.

* :class:`SecurityHeaders` (pure ASGI middleware, outermost): each HTTP response gets
  :data:`SECURITY_HEADERS` unless it set that header itself; the one page that needs a looser
  policy (the offline ``/docs``, :mod:`.api_docs`) sets :data:`DOCS_CSP`. WebSocket and lifespan
  scopes pass untouched, and a response's body (streamed or not) is never read or buffered.
* :func:`server_error`: the 500 for an unhandled exception carries the same headers (starlette
  sends it from outside every middleware).

``'self'`` in ``default-src`` covers the dashboard's ``ws://``/``wss://`` connection to its own host
and port (CSP level 3; tests/test_dashboard.py checks it in Chromium).
"""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import PlainTextResponse
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

#: Every response: scripts, styles, images, fonts and connections (ws: included) only from this
#: origin and never inline; no plugins, no <base>, forms submit only here, never framed.
STRICT_CSP = "default-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
#: The /docs page only: its stylesheet's icons are data: images, and Swagger UI's markdown renders
#: table alignment as style attributes (style elements and stylesheets stay 'self' only).
DOCS_CSP = f"{STRICT_CSP}; style-src-attr 'unsafe-inline'; img-src 'self' data:"

SECURITY_HEADERS: dict[str, str] = {
    "Content-Security-Policy": STRICT_CSP,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",  # frame-ancestors for browsers without CSP level 2
    "Referrer-Policy": "no-referrer",
}


class SecurityHeaders:
    """ASGI middleware: adds :data:`SECURITY_HEADERS` to each HTTP response that lacks them."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in SECURITY_HEADERS.items():
                    headers.setdefault(name, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)


async def server_error(request: Request, exc: Exception) -> PlainTextResponse:
    """Starlette's plain 500, with :data:`SECURITY_HEADERS`. The exception still reaches uvicorn,
    which logs it and closes the connection: ``Connection: close`` tells the client first."""
    return PlainTextResponse("Internal Server Error", status_code=500,
                             headers={**SECURITY_HEADERS, "Connection": "close"})
