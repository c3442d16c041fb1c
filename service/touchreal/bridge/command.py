"""``touchreal gateway``: a stateless /v1/stream server fed from NATS (docs/scale-out.md); and
``touchreal gateway credentials``: a gateway's own broker credentials (:mod:`.credentials`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import auth


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gateway", help="serve /v1/stream to many clients from a sensor published on NATS")
    p.add_argument("--nats", default=None, help="NATS URL(s), comma-separated (TOUCHREAL_GATEWAY_NATS; "
                   "default nats://127.0.0.1:4222)")
    p.add_argument("--sensor-id", default=None, help="the publisher's --sensor-id (TOUCHREAL_GATEWAY_SENSOR_ID)")
    p.add_argument("--gateway-id", default=None, help="this gateway's identity on the broker: its demand subject "
                   "touchreal.<sensor>.demand.<ID>, which its credentials must allow (TOUCHREAL_GATEWAY_GATEWAY_ID; "
                   "default HOSTNAME-PORT)")
    p.add_argument("--host", default=None, help="bind address (default 127.0.0.1; TOUCHREAL_GATEWAY_HOST)")
    p.add_argument("--port", type=int, default=None, help="port (default 8766; TOUCHREAL_GATEWAY_PORT)")
    p.add_argument("--log-level", default="warning", help="uvicorn log level")
    auth.add_arguments(p)
    p.set_defaults(func=run)
    tools = p.add_subparsers(dest="gateway_command", metavar="{credentials}")
    c = tools.add_parser("credentials", help="issue a gateway's broker credentials: an nkey seed file, and the "
                         "broker's user entry allowing it demand under its id only")
    c.add_argument("--id", required=True, help="the gateway's id (its --gateway-id)")
    c.add_argument("--out", required=True, type=Path, help="directory for ID.nk (the seed, 0600) and ID.pub")
    c.set_defaults(func=issue_credentials)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from ..server.app import uvicorn_config
    from .gateway import Gateway, GatewaySettings, create_gateway_app

    overrides = {k: v for k, v in (("nats", args.nats), ("sensor_id", args.sensor_id), ("gateway_id", args.gateway_id),
                                   ("host", args.host), ("port", args.port)) if v is not None}
    settings = GatewaySettings(**overrides)
    gateway = Gateway(settings, auth.from_args(args))
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal gateway {settings.gateway_id} for sensor {settings.sensor_id!r} from {gateway.where} "
          f"({gateway.auth.describe(gateway.servers)}): stream ws://{base}/v1/stream · status http://{base}/v1/status",
          flush=True)
    uvicorn.Server(uvicorn_config(create_gateway_app(gateway), settings.host, settings.port, args.log_level)).run()
    return 0


def issue_credentials(args: argparse.Namespace) -> int:
    """``touchreal gateway credentials``: issue, then say where the seed went and what the broker and the
    gateway need."""
    from .credentials import issue, user_entry

    path, public = issue(args.id, args.out)
    print(f"wrote {path} (the nkey seed of gateway {args.id}: give it to that gateway alone) and "
          f"{path.with_suffix('.pub')} (its public key {public})\n"
          f"broker (nats-server.conf, in authorization.users):\n  {user_entry(public, args.id)}\n"
          f"gateway: touchreal gateway --gateway-id {args.id} --nats-nkey {path} ...", flush=True)
    return 0
