"""Settings of the programs that serve ``/v1/stream``: flags over environment variables over defaults.

:class:`ServerSettings` is what every such program shares (bind address, client queues and limits,
keepalive, connection limits, Host/Origin allowlists); :class:`ServeSettings` (``touchreal serve``,
environment ``TOUCHREAL_<NAME>``) and the gateway's settings (:mod:`touchreal.bridge.gateway`,
``TOUCHREAL_GATEWAY_<NAME>``) extend it. Every field is a flag (``--state-dir``) and an environment
variable, fixed for the life of the process (:mod:`touchreal.commands.flags`; the docs' tables are
generated from the models: :mod:`touchreal.commands.settings_doc`). :class:`RuntimeConfig` is the
part a client may change at run time (``PATCH /v1/config``); it starts from the settings.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from touchreal_client.protocol import MAX_TAXELS

from ..params import WINDOW_RANGE_MS
from ..settings import CLASSES

log = logging.getLogger("touchreal.server")

#: Replay speeds (x real time) the service accepts: slow enough to step through, fast enough to
#: skim, and the replay's stamp arithmetic stays finite over any recording.
SPEED_RANGE = (0.01, 1000.0)
SCRIPT_SCENE_MAX_TAXELS = 256  #: sim_scene auto: the scripted scene up to this many taxels, the large one above
SOURCE_SPEC = "sim | replay:DATASET_DIR[:TRIAL_ID[,TRIAL_ID...]] | serial:PORT"

def _split_commas(v: object) -> object:
    return [x.strip() for x in v.split(",") if x.strip()] if isinstance(v, str) else v


#: A list given as one comma-separated value (flag or environment variable), not JSON.
CommaList = Annotated[list[str], NoDecode, BeforeValidator(_split_commas)]
CommaPaths = Annotated[list[Path], NoDecode, BeforeValidator(_split_commas)]


def parse_source(spec: str) -> tuple[str, str]:
    """``sim`` | ``replay:DIR[:ID,...]`` | ``serial:PORT`` -> (kind, argument); ValueError otherwise."""
    kind, _, arg = spec.partition(":")
    if kind == "sim" and not arg:
        return kind, ""
    if kind in ("replay", "serial") and arg:
        return kind, arg
    raise ValueError(f"source must be 'sim', 'replay:DATASET_DIR[:TRIAL_ID,...]' or 'serial:PORT', got {spec!r}")


class ServerSettings(BaseSettings):
    """What every program serving ``/v1/stream`` has: flag ``--NAME``, environment ``<PREFIX><NAME>``."""

    model_config = SettingsConfigDict(extra="ignore")

    # -- where it listens, what it logs
    host: str = Field(default="127.0.0.1", description="bind address")
    port: int = Field(default=8765, ge=0, le=65535, description="port")
    log_level: Literal["critical", "error", "warning", "info", "debug", "trace"] = Field(
        default="warning", description="uvicorn log level")

    # -- clients and their queues
    queue_frames: int = Field(default=512, ge=2, le=100000, description="frames queued per client before dropping "
                              "(512: 2.6 s of 5 ms hops)")
    slow_timeout_s: float = Field(default=2.0, gt=0, description="a client whose queue stays full, or that takes no "
                                  "frame while frames wait, this long is closed (4008)")
    max_frame_age_ms: float = Field(default=250.0, ge=0.0, le=60000.0, description="a frame queued for a client longer "
                                    "than this is dropped (counted, a seq gap) rather than sent late; 0 = no limit")
    max_clients: int = Field(default=1000, ge=1, description="WebSocket clients at once (more: close 1013)")

    # -- keepalive
    ping_interval_s: float = Field(default=20.0, gt=0, le=3600, description="WebSocket keepalive: a ping to each "
                                   "client this often (s)")
    ping_timeout_s: float = Field(default=20.0, gt=0, le=3600, description="a client that does not answer a ping "
                                  "within this time is closed with 1011 (s)")

    # -- who may connect
    allowed_hosts: CommaList = Field(default_factory=lambda: ["127.0.0.1", "localhost"], description="Host header "
                                     "values served (others: 400), e.g. the name behind a proxy; * = any")
    allowed_origins: CommaList = Field(default_factory=list, description="browser origins (scheme://host[:port]) "
                                       "that may open /v1/stream besides the server's own; * = any")
    forwarded_allow_ips: CommaList = Field(default_factory=list, description="addresses of reverse proxies whose "
                                           "X-Forwarded-For names the client (failed logins are throttled per client "
                                           "address); empty = the TCP peer is the client")

    # -- HTTP connections
    header_timeout_s: float = Field(default=10.0, gt=0, le=300, description="a connection that has not sent "
                                    "complete request headers this long after connecting (or after its last "
                                    "response) is closed")
    send_buffer_bytes: int = Field(default=65536, ge=0, le=1 << 26, description="kernel send buffer of each "
                                   "connection (SO_SNDBUF; 0 = the kernel's autotuning, which lets a slow reader "
                                   "fall seconds behind in buffers the server cannot age)")
    keep_alive_s: int = Field(default=5, ge=1, le=300, description="an idle HTTP keep-alive connection is closed "
                              "after this")
    max_header_bytes: int = Field(default=16384, ge=1024, le=1 << 20, description="largest request head "
                                  "(request line + headers, bytes; h11's max incomplete event size)")
    limit_concurrency: int = Field(default=1200, ge=10, description="open connections (HTTP + WebSocket) before new "
                                   "requests get 503; keep it above max_clients")


class ServeSettings(ServerSettings):
    """Every setting of ``touchreal serve``: flag ``--NAME`` (``_`` -> ``-``), environment ``TOUCHREAL_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_", extra="ignore")

    # -- the source
    source: str = Field(default="sim", description=SOURCE_SPEC)
    taxels: int = Field(default=1, ge=1, le=MAX_TAXELS, description="taxels of the simulated e-skin / serial device")
    speed: float = Field(default=1.0, ge=SPEED_RANGE[0], le=SPEED_RANGE[1], description="replay speed (x real time)")
    loop: bool = Field(default=False, description="replay: start again after the last trial")
    sim_scene: Literal["auto", "script", "large"] = Field(default="auto", description="the simulated e-skin's scene: "
                                                           "script (presses, vibrations and slides over the centre and "
                                                           "corner taxels), large (probes and objects pressing, rolling "
                                                           "and sliding over the skin, sim_touched of it at a time); auto: "
                                                           f"script up to {SCRIPT_SCENE_MAX_TAXELS} taxels, large above")
    sim_touched: float = Field(default=0.05, ge=0.0, le=1.0, description="the large scene's touched fraction")
    seed: int = Field(default=0, description="seed of the simulated e-skin")
    sim_t0_s: float | None = Field(default=None, description="sensor clock of the simulated e-skin's first tick (s)")

    # -- what is computed, and how
    params: Path | None = Field(default=None, description="initial parameter file (default: last active, else shipped)")
    population: str | None = Field(default=None, max_length=4096, description="spikes of an afferent population "
                                   "over the taxels instead of one afferent per taxel and class: 'fingertip' (the "
                                   "default plan, model variants matched at start) or a plan file from `touchreal "
                                   "population plan`; spikes then address afferents (protocol version 2, "
                                   "docs/population.md)")
    hop_ms: float = Field(default=5.0, ge=1.0, le=1000.0, description="hop (ms): the source hands over samples and "
                          "the SingleTact-only and short-window classes go out this often (at most update_ms); "
                          "long windows keep update_ms (docs/architecture.md, Latency)")
    taxel_block: int = Field(default=256, ge=0, le=4096, description="taxels per preprocessing block of dense "
                             "compute: a block whose taxels nobody subscribes to runs nothing, and each block costs a "
                             "fixed ~130 us per 5 ms hop (docs/benchmarks.md, Encoder); 0 = one block. A larger skin "
                             "runs activity-driven (unless --dense), taxel by taxel")
    compute_dtype: Literal["float64", "float32"] = Field(default="float64", description="arithmetic of the "
                                                        "preprocessing: float32 takes ~40 % less CPU at 4096 taxels and "
                                                        "gave the same spikes on the measured sets (docs/benchmarks.md, Encoder)")
    dense: bool = Field(default=False, description="run every demanded taxel block on every update; by default a "
                        "skin larger than one block runs only the taxels a contact has woken (activity-driven compute, "
                        "docs/architecture.md), a single block always runs")
    max_lag_ms: float = Field(default=250.0, ge=10.0, le=60_000.0, description="real time, or honest about it: a "
                              "chunk whose spikes would leave more than this (ms) after its oldest sample is dropped "
                              "with the backlog behind it and the pipeline restarts; clients see a seq gap and a "
                              "restarted, source_gap frame, /metrics counts it and health says degraded "
                              "(docs/service.md, How it runs)")

    # -- writes: who may, what they may open, how large
    token: str | None = Field(default=None, description="bearer token required by write endpoints; unset or empty = "
                              "writes open to whoever reaches the port")
    state_dir: Path = Field(default=Path("touchreal-state"), description="parameter history and user models")
    max_body_bytes: int = Field(default=1 << 20, ge=1024, le=1 << 30, description="largest request body (bytes); "
                                "larger ones get 413 without being read")
    source_changes: bool = Field(default=True, description="PATCH /v1/config may change source, taxels, speed, loop")
    data_roots: CommaPaths = Field(default_factory=list, description="folders under which PATCH "
                                                        "/v1/config may open replay: datasets, besides "
                                                        "STATE_DIR/datasets and serve's own --source folder")
    serial_urls: bool = Field(default=False, description="allow pyserial URLs (spy://, socket://, loop://...) as "
                              "serial: ports; they can reach files and hosts")

    # -- scale-out (docs/scale-out.md)
    publish: str | None = Field(default=None, description="also publish the frames to this NATS URL "
                                "(docs/scale-out.md), e.g. nats://127.0.0.1:4222")
    sensor_id: str | None = Field(default=None, description="with --publish: subjects touchreal.<ID>.*")
    publish_all: bool = Field(default=False, description="with --publish: every class and taxel, whatever the "
                              "gateways forward as demand")
    retain_s: float = Field(default=0.0, ge=0.0, le=3600.0, description="with --publish: keep the last S seconds of "
                            "frames in an in-memory JetStream stream touchreal_<ID> for late joiners")

    @field_validator("source")
    @classmethod
    def _source(cls, v: str) -> str:
        parse_source(v)
        return v

    @field_validator("token")
    @classmethod
    def _token(cls, v: str | None) -> str | None:
        if v == "":
            log.warning("the token is empty: treated as no token, write endpoints are open")
            return None
        return v

    def runtime_config(self) -> "RuntimeConfig":
        """The run-time config the service starts with."""
        return RuntimeConfig(source=self.source, taxels=self.taxels, speed=self.speed, loop=self.loop)


class RuntimeConfig(BaseModel):
    """What ``GET/PATCH /v1/config`` shows and changes. Changing ``source`` or ``taxels`` restarts
    the source; ``update_ms`` or ``window_ms`` restart the pipeline; ``classes`` only changes what is
    computed (classes outside it are never encoded, whoever subscribes)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    source: str = Field(default="sim", max_length=4096, description=SOURCE_SPEC)
    taxels: int = Field(default=1, ge=1, le=MAX_TAXELS, description="taxels of the simulated e-skin / serial device")
    speed: float = Field(default=1.0, ge=SPEED_RANGE[0], le=SPEED_RANGE[1], allow_inf_nan=False,
                         description="replay speed (x real time)")
    loop: bool = Field(default=False, description="replay: start again after the last trial")
    classes: list[str] = Field(default_factory=lambda: list(CLASSES), max_length=len(CLASSES),
                               description="classes the service may compute")


class ConfigPatch(BaseModel):
    """A partial :class:`RuntimeConfig` (``PATCH /v1/config``); strict types (``loop: 0`` is not a bool)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

    source: str | None = Field(default=None, max_length=4096, description=SOURCE_SPEC)
    taxels: int | None = Field(default=None, ge=1, le=MAX_TAXELS)
    speed: float | None = Field(default=None, ge=SPEED_RANGE[0], le=SPEED_RANGE[1], description="replay speed (x real time)")
    loop: bool | None = None
    update_ms: float | None = Field(default=None, ge=1.0, le=1000.0)
    window_ms: float | None = Field(default=None, ge=WINDOW_RANGE_MS[0], le=WINDOW_RANGE_MS[1])
    classes: list[str] | None = Field(default=None, max_length=len(CLASSES))
