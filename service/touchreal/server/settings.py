"""Service settings: command-line flags over ``TOUCHREAL_*`` environment variables over defaults.

:class:`ServeSettings` is fixed for the life of the process; :class:`RuntimeConfig` is the part a
client may change at run time (``PATCH /v1/config``).
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from ..settings import CLASSES


class ServeSettings(BaseSettings):
    """Process-wide settings of ``touchreal serve`` (environment: ``TOUCHREAL_<NAME>``)."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(default=8765, ge=0, le=65535)
    token: str | None = Field(default=None, description="bearer token required by write endpoints; None = open")
    state_dir: Path = Field(default=Path("touchreal-state"), description="parameter history and user models")
    params: Path | None = Field(default=None, description="initial parameter file (default: last active, else shipped)")
    queue_frames: int = Field(default=512, ge=2, le=100000, description="frames queued per client before dropping "
                              "(512: 2.6 s of 5 ms hops)")
    slow_timeout_s: float = Field(default=2.0, gt=0, description="a client whose queue stays full this long is closed")
    max_clients: int = Field(default=1000, ge=1)
    taxel_block: int = Field(default=64, ge=0, le=4096, description="taxels per preprocessing block: a block whose "
                             "taxels nobody subscribes to runs nothing (docs/benchmarks.md, Demand); 0 = one block")
    hop_ms: float = Field(default=5.0, ge=1.0, le=1000.0, description="hop (ms): the source hands over samples and "
                          "the SingleTact-only and short-window classes go out this often (at most update_ms); "
                          "long windows keep update_ms (docs/architecture.md, Latency)")
    seed: int = 0
    sim_t0_s: float | None = Field(default=None, description="sensor clock of the simulated e-skin's first tick (s)")


class RuntimeConfig(BaseModel):
    """What ``GET/PATCH /v1/config`` shows and changes. Changing ``source`` or ``taxels`` restarts
    the source; ``update_ms`` or ``window_ms`` restart the pipeline; ``classes`` only changes what is
    computed (classes outside it are never encoded, whoever subscribes)."""

    model_config = ConfigDict(extra="forbid")

    source: str = Field(default="sim", description="sim | replay:DATASET_DIR[:TRIAL_ID[,TRIAL_ID...]] | serial:PORT")
    taxels: int = Field(default=1, ge=1, le=4096, description="taxels of the simulated e-skin / serial device")
    speed: float = Field(default=1.0, gt=0.0, le=1000.0, description="replay speed (x real time)")
    loop: bool = Field(default=False, description="replay: start again after the last trial")
    classes: list[str] = Field(default_factory=lambda: list(CLASSES), description="classes the service may compute")


class ConfigPatch(BaseModel):
    """A partial :class:`RuntimeConfig` (``PATCH /v1/config``)."""

    model_config = ConfigDict(extra="forbid")

    source: str | None = None
    taxels: int | None = Field(default=None, ge=1, le=4096)
    speed: float | None = Field(default=None, gt=0.0, le=1000.0)
    loop: bool | None = None
    update_ms: float | None = Field(default=None, ge=1.0, le=1000.0)
    window_ms: float | None = Field(default=None, ge=4.0, le=512.0)
    classes: list[str] | None = None
