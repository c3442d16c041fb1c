"""REST helpers over httpx (async): configuration, parameters, decoders, health.

Reads are open; writes (``patch_config``, ``put_params``, ``rollback``) send
``Authorization: Bearer <token>`` when the client has a token. Errors become exceptions that say
what to do (:mod:`touchreal_client.errors`): a missing token is an :class:`AuthError`, an invalid
parameter set a :class:`ParamsRejected` listing every bad field.
"""

from __future__ import annotations

import asyncio
import json
import os
from pathlib import Path
from typing import Any

import httpx

from .errors import AuthError, NotFound, ParamsRejected, RequestError, ServiceUnavailable

JSON = dict[str, Any]


def _error_class(status: int) -> type[RequestError]:
    return {401: AuthError, 403: AuthError, 404: NotFound, 422: ParamsRejected}.get(status, RequestError)


def load_params(params: JSON | str | os.PathLike[str]) -> JSON:
    """A parameter set as a dict: a dict as is, else the path of a JSON file (``touchreal fit`` output)."""
    if isinstance(params, dict):
        return params
    path = Path(params)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read parameter file {path}: {exc.strerror}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a parameter file is a JSON object")
    return data


class AsyncRest:
    """The ``/v1`` REST API of one service. ``base_url``: ``http://HOST:PORT``."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 10.0,
                 transport: httpx.AsyncBaseTransport | None = None):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.base_url = base_url.rstrip("/")
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=headers, timeout=timeout_s, transport=transport)

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _request(self, method: str, path: str, **kw: Any) -> httpx.Response:
        try:
            r = await self._http.request(method, path, **kw)
        except httpx.TransportError as exc:
            raise ServiceUnavailable(f"{method} {self.base_url}{path}: {exc!r}") from exc
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except (ValueError, AttributeError):
                detail = r.text
            raise _error_class(r.status_code)(method, path, r.status_code, detail)
        return r

    async def _json(self, method: str, path: str, **kw: Any) -> Any:
        return (await self._request(method, path, **kw)).json()

    # -- health ---------------------------------------------------------------------------------
    async def health(self) -> JSON:
        """Liveness (``GET /v1/health``): ``{"status", "session"}``; raises on 503."""
        return await self._json("GET", "/v1/health")

    async def ready(self) -> tuple[bool, str]:
        """Readiness (``GET /v1/ready``): (ready, reason); 503 is an answer here, not an error."""
        try:
            r = await self._http.get("/v1/ready")
        except httpx.TransportError as exc:
            raise ServiceUnavailable(f"GET {self.base_url}/v1/ready: {exc!r}") from exc
        body = r.json()
        return bool(body.get("ready")), str(body.get("reason", ""))

    async def wait_ready(self, timeout_s: float = 60.0, poll_s: float = 0.2) -> None:
        """Wait until the service is up and ready (source streaming, pipeline warm); raises
        :class:`ServiceUnavailable` with the last reason after ``timeout_s``."""
        loop = asyncio.get_running_loop()
        deadline, reason = loop.time() + timeout_s, "not reached"
        while loop.time() < deadline:
            try:
                ok, reason = await self.ready()
            except ServiceUnavailable as exc:
                ok, reason = False, str(exc)
            if ok:
                return
            await asyncio.sleep(poll_s)
        raise ServiceUnavailable(f"{self.base_url} not ready after {timeout_s:g} s: {reason}")

    async def status(self) -> JSON:
        return await self._json("GET", "/v1/status")

    async def metrics(self) -> str:
        """Prometheus text exposition (``GET /metrics``)."""
        return (await self._request("GET", "/metrics")).text

    # -- configuration --------------------------------------------------------------------------
    async def config(self) -> JSON:
        return await self._json("GET", "/v1/config")

    async def patch_config(self, **changes: Any) -> JSON:
        """Change e.g. ``window_ms`` (the causal PVDF window), ``update_ms``, ``source``, ``taxels``,
        ``classes``; returns ``{"config", "restarted"}``. Needs the token when the service has one."""
        return await self._json("PATCH", "/v1/config", json=changes)

    # -- parameters -----------------------------------------------------------------------------
    async def params(self) -> JSON:
        """The active parameter set: ``{"rev", "sha256", "params"}``."""
        return await self._json("GET", "/v1/params")

    async def put_params(self, params: JSON | str | os.PathLike[str]) -> JSON:
        """Upload a parameter set (dict or JSON file); returns ``{"rev", "sha256"}``.
        Raises :class:`ParamsRejected` listing every invalid field; the service keeps its old set."""
        return await self._json("PUT", "/v1/params", json=load_params(params))

    async def params_history(self) -> JSON:
        return await self._json("GET", "/v1/params/history")

    async def rollback(self, rev: int) -> JSON:
        return await self._json("POST", "/v1/params/rollback", json={"rev": rev})

    # -- decoders -------------------------------------------------------------------------------
    async def decoders(self) -> list[JSON]:
        """Installed decoders (``GET /v1/decoders``): one metadata dict each."""
        body = await self._json("GET", "/v1/decoders")
        return body["decoders"] if isinstance(body, dict) and "decoders" in body else body

    async def decoder(self, name: str) -> JSON:
        """One decoder's metadata (``GET /v1/decoders/{name}``)."""
        return await self._json("GET", f"/v1/decoders/{name}")

    async def download_model(self, name: str, dest: str | os.PathLike[str] | None = None) -> bytes:
        """The decoder's ONNX file (``GET /v1/decoders/{name}/model.onnx``); also written to ``dest``
        when given. Run it with onnxruntime and :mod:`touchreal_client.features`."""
        data = (await self._request("GET", f"/v1/decoders/{name}/model.onnx")).content
        if dest is not None:
            Path(dest).write_bytes(data)
        return data
