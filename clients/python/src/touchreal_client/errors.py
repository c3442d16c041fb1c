"""Errors raised by the client: one base class, one subclass per thing a caller can act on."""

from __future__ import annotations

from typing import Any


class TouchRealError(Exception):
    """Base class of every error this package raises."""


class ServiceUnavailable(TouchRealError):
    """The service could not be reached (connection refused, timeout, DNS)."""


class RequestError(TouchRealError):
    """The service answered a REST request with an error status; ``status`` and ``detail`` say why."""

    def __init__(self, method: str, path: str, status: int, detail: Any):
        self.method, self.path, self.status, self.detail = method, path, status, detail
        super().__init__(f"{method} {path}: HTTP {status}: {_detail_text(detail)}")


class AuthError(RequestError):
    """401: a write endpoint needs ``Authorization: Bearer <token>`` (pass ``token=`` to the client)."""


class NotFound(RequestError):
    """404: no such decoder, revision or path."""


class ParamsRejected(RequestError):
    """422: the parameter set (or request body) is invalid; ``errors`` lists ``(field, message)`` for
    every bad field. The service keeps its previous parameters."""

    def __init__(self, method: str, path: str, status: int, detail: Any):
        self.errors: list[tuple[str, str]] = _field_errors(detail)
        super().__init__(method, path, status, detail)

    def __str__(self) -> str:
        lines = [f"{self.method} {self.path}: the service rejected the request ({len(self.errors)} invalid field(s)):"]
        lines += [f"  {loc}: {msg}" for loc, msg in self.errors]
        return "\n".join(lines)


class StreamClosed(TouchRealError):
    """The stream ended for good: the server closed it with ``code`` (docs/stream-protocol.md, close
    codes) and the client does not reconnect (a fatal code, or reconnecting is off or exhausted)."""

    def __init__(self, code: int | None, reason: str):
        self.code, self.reason = code, reason
        super().__init__(f"stream closed (code {code}): {reason}" if code is not None else f"stream closed: {reason}")


class StreamError(TouchRealError):
    """The server answered a ``subscribe`` or ``time`` message with an ``error`` message."""

    def __init__(self, code: str, message: str):
        self.code = code
        super().__init__(f"{code}: {message}")


def _field_errors(detail: Any) -> list[tuple[str, str]]:
    if isinstance(detail, list):
        out = []
        for e in detail:
            if isinstance(e, dict):
                loc = ".".join(str(p) for p in e.get("loc", ()) if p != "body")
                out.append((loc or "(body)", str(e.get("msg", e))))
            else:
                out.append(("(body)", str(e)))
        return out
    return [("(body)", _detail_text(detail))]


def _detail_text(detail: Any) -> str:
    if isinstance(detail, list):
        return "; ".join(f"{loc}: {msg}" for loc, msg in _field_errors(detail))
    return str(detail)
