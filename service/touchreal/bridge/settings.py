"""``touchreal gateway``'s settings: a light module (no NATS or web imports), so the command line
builds its flags without loading the gateway."""

from __future__ import annotations

import re
import secrets
import socket

from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from ..server.settings import ServerSettings
from . import subjects


def default_gateway_id(port: int) -> str:
    """``HOSTNAME-PORT`` as one subject token: the same after a restart on the same host and port (a
    pod's hostname is its name); with port 0 (any free port) ``HOSTNAME-`` and 6 random hex digits."""
    host = re.sub(r"[^A-Za-z0-9_-]+", "-", socket.gethostname()).strip("-")[:57] or "gateway"
    return f"{host}-{port or secrets.token_hex(3)}"



class GatewaySettings(ServerSettings):
    """Every setting of ``touchreal gateway``: flag ``--NAME``, environment ``TOUCHREAL_GATEWAY_<NAME>``
    (the stream settings it shares with ``serve``: :class:`~touchreal.server.settings.ServerSettings`)."""

    model_config = SettingsConfigDict(env_prefix="TOUCHREAL_GATEWAY_", extra="ignore")

    port: int = Field(default=8766, ge=0, le=65535, description="port (8766: beside a service on its default 8765)")
    nats: str = Field(default="nats://127.0.0.1:4222", description="NATS server URL(s), comma-separated")
    sensor_id: str = Field(default="sensor", description="the publisher's --sensor-id")
    gateway_id: str = Field(default="", description="this gateway's identity on the broker: it announces demand on "
                            "touchreal.<sensor>.demand.<gateway_id>, which its broker credentials must allow; "
                            "default HOSTNAME-PORT")
    pending_frames: int = Field(default=1024, ge=1, description="frames NATS may buffer for this gateway before "
                                "dropping them (each loss becomes a gap its clients see)")
    demand_interval_s: float = Field(default=1.0, gt=0, description="how often the demand is re-announced (s)")

    @model_validator(mode="after")
    def _identity(self) -> GatewaySettings:
        self.gateway_id = subjects.check_gateway_id(self.gateway_id or default_gateway_id(self.port))
        return self
