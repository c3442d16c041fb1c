"""The ``/v1`` REST surface: thin handlers over the :class:`~.service.Service` (OpenAPI at /openapi.json).

Reads are open; writes (PATCH /v1/config, PUT /v1/params, POST /v1/params/rollback, PUT /v1/context) need
``Authorization: Bearer <token>`` when the service has a token (``--token`` / ``TOUCHREAL_TOKEN``),
checked before the body is read, and bodies are bounded before they are parsed
(:class:`~.security.BodyGuard`); 422s name the field and never echo the input.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request, Response
from fastapi.responses import FileResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, ConfigDict, Field
from touchreal_client.schema import asyncapi as stream_contract

from ..decoding.model import DecoderModelError
from ..params import EncoderParams, ParamsError
from .params_store import params_sha256
from .security import token_ok
from .service import SourceOpenError
from .sources import SourceRefused
from .settings import ConfigPatch

router = APIRouter()
_bearer = HTTPBearer(auto_error=False, description="required by write endpoints when the service has a token")


def service_of(request: Request):
    """The service: what the write routes change."""
    return request.app.state.service


def view_of(request: Request):
    """What the service reports: what the read routes show (:class:`~.view.ServiceView`)."""
    return request.app.state.service.view


def require_token(request: Request, cred: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> None:
    """The write endpoints' token check, as OpenAPI shows it (:class:`~.security.BodyGuard` applies
    the same check before a body is read)."""
    if not token_ok(service_of(request).settings.token, request.headers.get("authorization")):
        raise HTTPException(401, "this endpoint needs 'Authorization: Bearer <token>'",
                            headers={"WWW-Authenticate": "Bearer"})


class Health(BaseModel):
    status: str = Field(description="ok | degraded (the parameters in force are a fallback, or compute shed load in the "
                        "last 10 s) | failed")
    session: str
    reason: str | None = Field(default=None, description="why degraded or failed")


class Ready(BaseModel):
    ready: bool
    reason: str


class ParamsInfo(BaseModel):
    rev: int
    sha256: str
    params: dict[str, Any] | None = None


class Rollback(BaseModel):
    model_config = ConfigDict(extra="forbid")

    rev: int = Field(ge=1, le=2**31, strict=True, description="an earlier revision from GET /v1/params/history")


class ScanContext(BaseModel):
    """What a robot knows of the scene that the decoders may read."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    speed_mm_s: float | None = Field(default=None, gt=0.0, le=1000.0, strict=True,
                                     description="scanning speed of the skin across the surface (mm/s) while it slides; "
                                     "null: not scanning (decoders that read a speed output NaN)")


@router.get("/v1/health", response_model=Health, tags=["health"], responses={503: {"model": Health}})
def health(request: Request) -> Any:
    """Liveness: the process serves and its acquisition thread has not failed; ``degraded`` while a
    parameter set that failed has been replaced by a fallback, or for 10 s after compute shed load
    (the reason says which)."""
    svc = service_of(request)
    state = svc.view.health()
    status, _, reason = state.partition(": ")
    if status == "failed":
        reason = svc.runtime.error
    return JSONResponse(Health(status=status, session=svc.session, reason=reason or None).model_dump(),
                        status_code=503 if status == "failed" else 200)


@router.get("/v1/ready", response_model=Ready, tags=["health"], responses={503: {"model": Ready}})
def ready(request: Request) -> Any:
    """Readiness: the source delivers and the pipeline is warm (JIT compiled, first update done)."""
    ok, reason = view_of(request).ready()
    return JSONResponse(Ready(ready=ok, reason=reason).model_dump(), status_code=200 if ok else 503)


@router.get("/v1/status", tags=["service"])
def status(request: Request) -> dict[str, Any]:
    """Source state and counters, pipeline state, current demand, per-client queues and drops; `nats` when publishing."""
    return view_of(request).status()


@router.get("/v1/config", tags=["config"])
def get_config(request: Request) -> dict[str, Any]:
    return view_of(request).config_view()


@router.patch("/v1/config", tags=["config"], dependencies=[Depends(require_token)],
              responses={400: {"description": "invalid value"}, 401: {"description": "token missing or wrong"},
                         403: {"description": "a source outside what this service lets clients open"},
                         409: {"description": "the source cannot be opened; the previous source runs again"},
                         422: {"description": "invalid value, or the new preprocessing does not run"}})
async def patch_config(patch: ConfigPatch, request: Request) -> dict[str, Any]:
    """Change the source, taxels, replay speed/loop, update interval, default window or computed classes;
    the answer says what was restarted (``source``, ``pipeline``)."""
    try:
        return await service_of(request).patch_config(patch)
    except SourceRefused as exc:
        raise HTTPException(403, str(exc)) from exc
    except SourceOpenError as exc:
        raise HTTPException(409, str(exc)) from exc
    except ParamsError as exc:
        raise HTTPException(422, str(exc)) from exc
    except ValueError as exc:
        raise HTTPException(400, str(exc)) from exc


@router.get("/v1/params", response_model=ParamsInfo, tags=["params"])
def get_params(request: Request) -> ParamsInfo:
    store = service_of(request).store
    rev, params = store.current
    return ParamsInfo(rev=rev, sha256=params_sha256(params), params=params.model_dump(by_alias=True, mode="json"))


@router.put("/v1/params", response_model=ParamsInfo, tags=["params"], dependencies=[Depends(require_token)],
            responses={401: {"description": "token missing or wrong"},
                       422: {"description": "invalid parameter set (every bad field is listed) or one that does not "
                                            "run (the dry run's reason); the old set stays"}})
async def put_params(params: EncoderParams, request: Request) -> ParamsInfo:
    """Upload a parameter set (the versioned JSON of ``touchreal fit``). It is proved runnable (a dry run
    of the whole chain on silence, saturation and vibration), becomes active between two updates and is
    persisted in the state directory."""
    try:
        rev = await service_of(request).put_params(params)
    except ParamsError as exc:
        raise HTTPException(422, str(exc)) from exc
    return ParamsInfo(rev=rev, sha256=params_sha256(params))


@router.get("/v1/params/history", tags=["params"])
def params_history(request: Request) -> dict[str, Any]:
    store = service_of(request).store
    return {"active": store.active_rev, "revisions": [r.__dict__ for r in store.revisions]}


@router.post("/v1/params/rollback", response_model=ParamsInfo, tags=["params"], dependencies=[Depends(require_token)],
             responses={401: {"description": "token missing or wrong"}, 404: {"description": "no such revision"},
                        422: {"description": "that revision no longer validates or runs"}})
async def rollback(body: Rollback, request: Request) -> ParamsInfo:
    """Activate an earlier revision again (recorded as a new revision)."""
    svc = service_of(request)
    try:
        rev = await svc.rollback(body.rev)
    except KeyError as exc:
        raise HTTPException(404, str(exc.args[0])) from exc
    except ParamsError as exc:
        raise HTTPException(422, str(exc)) from exc
    return ParamsInfo(rev=rev, sha256=svc.store.info(rev).sha256)


@router.get("/v1/context", response_model=ScanContext, tags=["decoders"])
def get_context(request: Request) -> ScanContext:
    return ScanContext(speed_mm_s=service_of(request).scan_speed_mm_s)


@router.put("/v1/context", response_model=ScanContext, tags=["decoders"], dependencies=[Depends(require_token)],
            responses={401: {"description": "token missing or wrong"}, 422: {"description": "invalid value"}})
def put_context(body: ScanContext, request: Request) -> ScanContext:
    """The scanning speed decoders that read one (``texture_spatial``, docs/decoders.md) use from the next
    update on, until changed; null while the skin does not slide."""
    service_of(request).scan_speed_mm_s = body.speed_mm_s
    return body


@router.get("/v1/decoders", tags=["decoders"])
def decoders(request: Request) -> list[dict[str, Any]]:
    """Installed decoder models (shipped with the package, plus the state directory's models/):
    metadata, and a warning where the active parameters differ from the ones it was trained on."""
    return view_of(request).decoders_view()


@router.get("/v1/decoders/{name}", tags=["decoders"], responses={404: {"description": "no such decoder"}})
def decoder(name: str, request: Request) -> dict[str, Any]:
    for m in decoders(request):
        if m["name"] == name:
            return m
    raise HTTPException(404, f"no decoder model named {name!r}")


@router.get("/v1/decoders/{name}/model.onnx", tags=["decoders"], response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}}}, 404: {"description": "no such decoder"}})
def decoder_onnx(name: str, request: Request) -> FileResponse:
    """The ONNX file (metadata embedded): run it with onnxruntime on binned spike counts (docs/decoders.md)."""
    try:
        path = service_of(request).models.path(name)
    except DecoderModelError as exc:
        raise HTTPException(404, str(exc)) from exc
    return FileResponse(path, media_type="application/octet-stream", filename=f"{name}.onnx")


@router.get("/metrics", tags=["health"], response_class=Response)
def metrics(request: Request) -> Response:
    """Prometheus text exposition."""
    return Response(generate_latest(service_of(request).metrics.registry), media_type=CONTENT_TYPE_LATEST)


@router.get("/v1/asyncapi.json", tags=["stream"])
def asyncapi(request: Request) -> dict[str, Any]:
    """The AsyncAPI 3.0 document of the `/v1/stream` WebSocket, with JSON Schemas of every JSON message
    (shipped in the client package as `touchreal_client.schema`; prose in docs/stream-protocol.md)."""
    return stream_contract(request.url.netloc)
