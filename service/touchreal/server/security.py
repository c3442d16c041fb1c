"""Guards in front of the service's routes: what a request must be before any handler sees it.

* :class:`BodyGuard` (ASGI middleware): on a request that carries a body (every method but GET,
  HEAD, OPTIONS), the bearer token is checked first (401 without reading the body), then the
  body is counted while it is read (413 once it passes ``max_body_bytes``, whatever the
  Content-Length says), then a JSON body is checked for nesting depth and integer literal length
  (422) before FastAPI parses it.
* :func:`validation_error` : a 422 that names each bad field and never echoes the input, so NaN,
  Infinity or a huge value in a body cannot turn the answer into a 500.
* :func:`token_ok`: the one token comparison, shared by the middleware and the OpenAPI dependency.
* :func:`admit`: the Origin check of ``/v1/stream`` (a browser page of another origin, e.g. after
  DNS rebinding, gets 403); the Host allowlist is starlette's ``TrustedHostMiddleware`` (app.py).
"""

from __future__ import annotations

import json
import re
import secrets
from collections.abc import Awaitable, Callable
from urllib.parse import urlsplit

import numpy as np
from fastapi import Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

MAX_JSON_DEPTH = 64  #: nesting levels of arrays/objects in a request body
MAX_INT_DIGITS = 1000  #: digits of an integer literal in a request body

_BODYLESS = {"GET", "HEAD", "OPTIONS"}
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def token_ok(token: str | None, authorization: str | None) -> bool:
    """Whether an ``Authorization`` header value satisfies ``token`` (None: no token, anything goes)."""
    if token is None:
        return True
    scheme, _, given = (authorization or "").partition(" ")
    return scheme.lower() == "bearer" and secrets.compare_digest(given.strip().encode(), token.encode())


def json_depth(body: bytes) -> int:
    """Deepest nesting of arrays/objects in a JSON text (strings skipped; no recursion, so any
    depth is measured without exhausting the stack)."""
    skeleton = np.frombuffer(_JSON_STRING.sub(b'""', body), np.uint8)
    steps = np.isin(skeleton, (ord("["), ord("{"))).astype(np.int64) - np.isin(skeleton, (ord("]"), ord("}")))
    return int(np.cumsum(steps).max(initial=0))


def _bounded_int(literal: str) -> int:
    if len(literal.lstrip("-")) > MAX_INT_DIGITS:
        raise ValueError(f"an integer literal has more than {MAX_INT_DIGITS} digits")
    return int(literal)


def json_problem(body: bytes) -> str | None:
    """Why a JSON body is refused before parsing (too deep, an oversized integer), else None.
    Syntax errors are left to FastAPI (its 422 says where)."""
    if json_depth(body) > MAX_JSON_DEPTH:
        return f"JSON nested deeper than {MAX_JSON_DEPTH} levels"
    try:
        json.loads(body, parse_int=_bounded_int)
    except ValueError as exc:
        return None if isinstance(exc, json.JSONDecodeError) else str(exc)
    return None


def _problem(status: int, detail: object, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


class BodyGuard:
    """ASGI middleware: token before body, a counted body limit, JSON shape limits (module doc).

    ``token()`` returns the service's token at request time (None: open)."""

    def __init__(self, app: ASGIApp, token: Callable[[], str | None], max_body_bytes: int):
        self.app, self.token, self.max_body_bytes = app, token, max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in _BODYLESS:
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if not token_ok(self.token(), headers.get("authorization")):
            await _problem(401, "this endpoint needs 'Authorization: Bearer <token>'",
                           {"WWW-Authenticate": "Bearer", "Connection": "close"})(scope, receive, send)
            return
        too_large = _problem(413, f"request body larger than {self.max_body_bytes} bytes", {"Connection": "close"})
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > self.max_body_bytes:
            await too_large(scope, receive, send)
            return
        body = await self._read(receive)
        if body is None:
            await too_large(scope, receive, send)
            return
        if body and "json" in headers.get("content-type", "json"):
            why = json_problem(body)
            if why is not None:
                await _problem(422, [{"loc": ["body"], "msg": why, "type": "json_invalid"}])(scope, receive, send)
                return
        await self.app(scope, _replay(body, receive), send)

    async def _read(self, receive: Receive) -> bytes | None:
        """The whole body, or None as soon as it passes the limit (the rest is never read)."""
        parts, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return b"".join(parts)
            chunk = msg.get("body", b"")
            size += len(chunk)
            if size > self.max_body_bytes:
                return None
            parts.append(chunk)
            if not msg.get("more_body", False):
                return b"".join(parts)


def _replay(body: bytes, receive: Receive) -> Callable[[], Awaitable[Message]]:
    """A ``receive`` that hands the app the buffered body once, then defers to the real one."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 listing each problem as ``{loc, msg, type}`` (the input is never echoed back)."""
    detail = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
              for e in exc.errors()]
    return _problem(422, detail)


def origin_allowed(origin: str | None, host: str | None, allowed: list[str]) -> bool:
    """A WebSocket handshake's ``Origin`` is acceptable: absent (not a browser), the page's own
    ``Host`` (same origin), or listed in ``allowed`` (``scheme://host[:port]``, or ``*``)."""
    if origin is None:
        return True
    if "*" in allowed or origin.rstrip("/") in allowed:
        return True
    return host is not None and urlsplit(origin).netloc.lower() == host.lower()


async def admit(ws: WebSocket) -> bool:
    """The Origin check of ``/v1/stream`` before the handshake is accepted: False after refusing it
    (HTTP 403). The allowlist is ``app.state.allowed_origins`` (none: same origin only)."""
    allowed = list(getattr(ws.app.state, "allowed_origins", ()))
    if origin_allowed(ws.headers.get("origin"), ws.headers.get("host"), allowed):
        return True
    await ws.close(code=1008)  # before accept: the server answers the handshake with 403
    return False
