"""``touchreal gateway``: a stateless /v1/stream server fed from NATS (docs/scale-out.md)."""

from __future__ import annotations

import argparse

from . import auth


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gateway", help="serve /v1/stream to many clients from a sensor published on NATS")
    p.add_argument("--nats", default=None, help="NATS URL(s), comma-separated (TOUCHREAL_GATEWAY_NATS; "
                   "default nats://127.0.0.1:4222)")
    p.add_argument("--sensor-id", default=None, help="the publisher's --sensor-id (TOUCHREAL_GATEWAY_SENSOR_ID)")
    p.add_argument("--host", default=None, help="bind address (default 127.0.0.1; TOUCHREAL_GATEWAY_HOST)")
    p.add_argument("--port", type=int, default=None, help="port (default 8766; TOUCHREAL_GATEWAY_PORT)")
    p.add_argument("--log-level", default="warning", help="uvicorn log level")
    auth.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from ..server.app import uvicorn_config
    from .gateway import Gateway, GatewaySettings, create_gateway_app

    overrides = {k: v for k, v in (("nats", args.nats), ("sensor_id", args.sensor_id), ("host", args.host),
                                   ("port", args.port)) if v is not None}
    settings = GatewaySettings(**overrides)
    gateway = Gateway(settings, auth.from_args(args))
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal gateway for sensor {settings.sensor_id!r} from {settings.nats}: stream ws://{base}/v1/stream · "
          f"status http://{base}/v1/status", flush=True)
    uvicorn.Server(uvicorn_config(create_gateway_app(gateway), settings.host, settings.port, args.log_level)).run()
    return 0
