"""``touchreal gateway``: a stateless /v1/stream server fed from NATS (docs/scale-out.md); and
``touchreal gateway credentials``: a gateway's own broker credentials (:mod:`.credentials`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from .flags import add_server_parser
    from ..bridge.settings import GatewaySettings

    p = add_server_parser(sub, "gateway", GatewaySettings, run,
                          help="serve /v1/stream to many clients from a sensor published on NATS",
                          description="Every flag also reads from the environment variable TOUCHREAL_GATEWAY_<FLAG>, "
                                      "the --nats-* flags from TOUCHREAL_NATS_<FLAG> (docs/scale-out.md, Settings).")
    tools = p.add_subparsers(dest="gateway_command", metavar="{credentials}")
    c = tools.add_parser("credentials", help="issue a gateway's broker credentials: an nkey seed file, and the "
                         "broker's user entry allowing it demand under its id only")
    c.add_argument("--id", required=True, help="the gateway's id (its --gateway-id)")
    c.add_argument("--out", required=True, type=Path, help="directory for ID.nk (the seed, 0600) and ID.pub")
    c.set_defaults(func=issue_credentials)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from .flags import model_from_args, nats_auth_from_args
    from ..server.app import uvicorn_config
    from ..bridge.gateway import Gateway, create_gateway_app
    from ..bridge.settings import GatewaySettings

    settings = model_from_args(GatewaySettings, args)
    gateway = Gateway(settings, nats_auth_from_args(args))
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal gateway {settings.gateway_id} for sensor {settings.sensor_id!r} from {gateway.where} "
          f"({gateway.auth.describe(gateway.servers)}): stream ws://{base}/v1/stream · status http://{base}/v1/status",
          flush=True)
    app = create_gateway_app(gateway)
    uvicorn.Server(uvicorn_config(app, settings.host, settings.port, settings.log_level)).run()
    return 0


def issue_credentials(args: argparse.Namespace) -> int:
    """``touchreal gateway credentials``: issue, then say where the seed went and what the broker and the
    gateway need."""
    from ..bridge.credentials import issue, user_entry

    path, public = issue(args.id, args.out)
    print(f"wrote {path} (the nkey seed of gateway {args.id}: give it to that gateway alone) and "
          f"{path.with_suffix('.pub')} (its public key {public})\n"
          f"broker (nats-server.conf, in authorization.users):\n  {user_entry(public, args.id)}\n"
          f"gateway: touchreal gateway --gateway-id {args.id} --nats-nkey {path} ...", flush=True)
    return 0
