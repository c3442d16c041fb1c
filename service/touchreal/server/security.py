"""Guards in front of the service's routes: what a request must be before any handler sees it.

* :class:`BodyGuard` (ASGI middleware): on a request that carries a body (every method but GET,
  HEAD, OPTIONS), a peer that failed authentication too often gets 429 (:class:`AuthThrottle`),
  then the bearer token is checked (401 without reading the body), then the body is counted while
  it is read (413 once it passes the route's limit, whatever the Content-Length says) and a JSON
  body's shape is checked as it arrives (:class:`JsonShape`: UTF-8, nesting depth, number literal
  length; 422) before FastAPI parses it. Every check is linear in the body and runs in slices of
  :data:`SCAN_SLICE_BYTES` with the event loop free between them, so no body holds the loop for
  more than a few milliseconds.
* :func:`validation_error`: a 422 that names each bad field and never echoes the input, so NaN,
  Infinity or a huge value in a body cannot turn the answer into a 500.
* :func:`token_ok`: the one token comparison (constant time whatever the lengths), shared by the
  middleware and the OpenAPI dependency.
* :func:`admit`: the Origin check of ``/v1/stream`` (a browser page of another origin, e.g. after
  DNS rebinding, gets 403); the Host allowlist is starlette's ``TrustedHostMiddleware`` (app.py).
"""

from __future__ import annotations

import asyncio
import codecs
import hashlib
import logging
import math
import secrets
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np
from fastapi import Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("touchreal.server")

MAX_JSON_DEPTH = 64  #: nesting levels of arrays/objects in a request body
MAX_NUMBER_CHARS = 1000  #: characters of one number literal in a request body (digits, sign, point, exponent)
SCAN_SLICE_BYTES = 64 * 1024  #: a body is checked this many bytes at a time, yielding to the event loop between
#: Bodies of the small write endpoints are bounded below the service's ``max_body_bytes`` (bytes).
ROUTE_BODY_LIMITS: Mapping[tuple[str, str], int] = {("POST", "/v1/params/rollback"): 1024,
                                                     ("PATCH", "/v1/config"): 16 * 1024,
                                                     ("PUT", "/v1/context"): 1024}

_BODYLESS = {"GET", "HEAD", "OPTIONS"}
#: byte classes of :class:`JsonShape`: 1 backslash, 2 quote, 3 opening bracket, 4 closing bracket, 5 number character
_CLASS = np.zeros(256, np.int8)
_CLASS[ord("\\")], _CLASS[ord('"')] = 1, 2
_CLASS[[ord("["), ord("{")]], _CLASS[[ord("]"), ord("}")]] = 3, 4
_CLASS[list(b"0123456789+-.eE")] = 5


def token_ok(token: str | None, authorization: str | None) -> bool:
    """Whether an ``Authorization`` header value satisfies ``token`` (None: no token, anything goes).
    Both sides are hashed first, so the comparison's time depends on neither's content nor length."""
    if token is None:
        return True
    scheme, _, given = (authorization or "").partition(" ")
    digest = hashlib.sha256(given.strip().encode("utf-8", "surrogateescape")).digest()
    return secrets.compare_digest(digest, hashlib.sha256(token.encode()).digest()) and scheme.lower() == "bearer"


def _run_before(is_run: np.ndarray, carried: int) -> np.ndarray:
    """Per byte: how many bytes of the run marked by ``is_run`` end right before it (``carried``: the
    run's length at the end of the previous slice)."""
    idx = np.arange(is_run.size, dtype=np.int64)
    last_other = np.maximum.accumulate(np.where(is_run, -1 - carried, idx))
    before = np.empty(is_run.size, np.int64)
    before[0] = carried
    before[1:] = idx[:-1] - last_other[:-1]
    return before


class JsonShape:
    """Sans-I/O: the shape of a JSON text fed in slices, in time linear in its length: whether it is
    UTF-8, its deepest nesting of arrays/objects and its longest number literal (strings skipped,
    escapes honoured across slice boundaries). Syntax errors are left to the parser."""

    def __init__(self) -> None:
        self._utf8 = codecs.getincrementaldecoder("utf-8")()
        self.utf8 = True
        self.in_string = False
        self.backslashes = 0  #: the backslash run at the end of what was fed
        self.depth = self.max_depth = 0
        self.number = self.max_number = 0  #: the number literal running at the end / the longest seen

    def feed(self, data: bytes, final: bool = False) -> None:
        try:
            self._utf8.decode(data, final)
        except UnicodeDecodeError:
            self.utf8 = False
        if not data:
            return
        cls = _CLASS[np.frombuffer(data, np.uint8)]
        quote = cls == 2
        quote &= _run_before(cls == 1, self.backslashes) % 2 == 0  # an escaped quote does not end a string
        opened = np.cumsum(quote, dtype=np.int64) + self.in_string
        outside = (opened % 2 == 0) & ~quote
        steps = ((cls == 3) & outside).astype(np.int64) - ((cls == 4) & outside)
        depth = np.cumsum(steps) + self.depth
        self.max_depth = max(self.max_depth, int(depth.max()))
        number = (cls == 5) & outside
        run = _run_before(number, self.number) + 1  # the number literal's length up to and including each byte
        self.max_number = max(self.max_number, int(np.where(number, run, 0).max()))
        self.number = int(run[-1]) if number[-1] else 0
        self.depth, self.in_string = int(depth[-1]), bool(opened[-1] % 2)
        tail = cls[::-1] != 1  # the backslash run at the end carries into the next slice
        self.backslashes = int(tail.argmax()) if tail.any() else self.backslashes + len(data)

    def problem(self) -> str | None:
        """Why the text is refused before parsing (None: parse it)."""
        if not self.utf8:
            return "the body is not valid UTF-8"
        if self.max_depth > MAX_JSON_DEPTH:
            return f"JSON nested deeper than {MAX_JSON_DEPTH} levels"
        if self.max_number > MAX_NUMBER_CHARS:
            return f"a number literal longer than {MAX_NUMBER_CHARS} characters"
        return None


@dataclass
class _Peer:
    failures: int = 0  #: failed authentications since the last success (or since they were forgotten)
    last_failure: float = 0.0
    blocked_until: float = 0.0


class AuthThrottle:
    """Sans-I/O: per peer address, failed authentications and the back-off they earn.

    The first :attr:`free` failures cost nothing; each further one blocks the peer for
    ``base_s * 2**(failures - free - 1)``, at most ``max_s``. While blocked, the peer's writes get 429
    with ``Retry-After`` *before* their token is looked at, so a blocked guesser learns nothing. A
    success clears the peer; failures are forgotten after ``forget_s`` without one. Other peers are
    never affected; at most ``max_peers`` are remembered (the longest quiet go first). Times in s of
    ``clock`` (monotonic)."""

    def __init__(self, free: int = 5, base_s: float = 1.0, max_s: float = 60.0, forget_s: float = 600.0,
                 max_peers: int = 10_000, clock: Callable[[], float] = time.monotonic):
        self.free, self.base_s, self.max_s, self.forget_s, self.max_peers = free, base_s, max_s, forget_s, max_peers
        self.clock = clock
        self._peers: OrderedDict[str, _Peer] = OrderedDict()

    def retry_after(self, peer: str) -> float:
        """Seconds the peer must still wait (0: it may try)."""
        p = self._peers.get(peer)
        return 0.0 if p is None else max(0.0, p.blocked_until - self.clock())

    def failed(self, peer: str) -> float:
        """Record a failure; returns the block it earned (s; 0 while failures are free)."""
        now = self.clock()
        p = self._peers.pop(peer, None)
        if p is None or now - p.last_failure > self.forget_s:
            p = _Peer()
        p.failures += 1
        p.last_failure = now
        block = 0.0 if p.failures <= self.free else min(self.max_s, self.base_s * 2 ** (p.failures - self.free - 1))
        p.blocked_until = now + block
        self._peers[peer] = p  # most recent last
        while len(self._peers) > self.max_peers:
            self._peers.popitem(last=False)
        return block

    def succeeded(self, peer: str) -> None:
        self._peers.pop(peer, None)


def _problem(status: int, detail: object, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


class BodyGuard:
    """ASGI middleware: throttled token check before the body, a counted body limit, JSON shape
    limits checked as the body arrives (module doc).

    ``token()`` returns the service's token at request time (None: open); ``on_auth(event)`` is told
    ``"failure"`` and ``"throttled"`` (metrics)."""

    def __init__(self, app: ASGIApp, token: Callable[[], str | None], max_body_bytes: int,
                 on_auth: Callable[[str], None] = lambda event: None, throttle: AuthThrottle | None = None):
        self.app, self.token, self.max_body_bytes, self.on_auth = app, token, max_body_bytes, on_auth
        self.throttle = throttle or AuthThrottle()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in _BODYLESS:
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        refusal = self._authenticate(scope, headers.get("authorization"))
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        limit = min(self.max_body_bytes, ROUTE_BODY_LIMITS.get((scope["method"], scope["path"]), self.max_body_bytes))
        too_large = _problem(413, f"request body larger than {limit} bytes", {"Connection": "close"})
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            await too_large(scope, receive, send)
            return
        shape = JsonShape() if "json" in headers.get("content-type", "json") else None
        body = await self._read(receive, limit, shape)
        if body is None:
            await too_large(scope, receive, send)
            return
        why = shape.problem() if shape is not None and body else None
        if why is not None:  # the rest of a refused body is never read
            await _problem(422, [{"loc": ["body"], "msg": why, "type": "json_invalid"}],
                           {"Connection": "close"})(scope, receive, send)
            return
        await self.app(scope, _replay(body, receive), send)

    def _authenticate(self, scope: Scope, authorization: str | None) -> JSONResponse | None:
        """None if the request may go on, else the answer: 429 for a peer in back-off, 401 for a wrong token."""
        token = self.token()
        if token is None:
            return None
        peer = (scope.get("client") or ("unknown", 0))[0]
        wait = self.throttle.retry_after(peer)
        if wait > 0:
            self.on_auth("throttled")
            return _problem(429, "too many failed authentications from this address; retry later",
                            {"Retry-After": str(math.ceil(wait)), "Connection": "close"})
        if token_ok(token, authorization):
            self.throttle.succeeded(peer)
            return None
        self.on_auth("failure")
        block = self.throttle.failed(peer)
        log.warning("failed authentication from %s on %s %s%s", peer, scope["method"], scope["path"],
                    f"; its writes are refused for {block:g} s" if block else "")
        return _problem(401, "this endpoint needs 'Authorization: Bearer <token>'",
                        {"WWW-Authenticate": "Bearer", "Connection": "close"})

    @staticmethod
    async def _read(receive: Receive, limit: int, shape: JsonShape | None) -> bytes | None:
        """The whole body, or None as soon as it passes ``limit`` (the rest is never read); ``shape``
        is fed as it arrives, a slice at a time with the event loop free between slices, and reading
        stops at the first problem it finds (what was read is returned)."""
        parts, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                break
            chunk = msg.get("body", b"")
            size += len(chunk)
            if size > limit:
                return None
            parts.append(chunk)
            if shape is not None:
                for i in range(0, len(chunk), SCAN_SLICE_BYTES):
                    shape.feed(chunk[i:i + SCAN_SLICE_BYTES])
                    if shape.problem() is not None:
                        return b"".join(parts)
                    await asyncio.sleep(0)
            if not msg.get("more_body", False):
                break
        if shape is not None:
            shape.feed(b"", final=True)
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
