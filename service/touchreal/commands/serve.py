"""``touchreal serve``: the service on a source (the simulated e-skin by default).

Its flags are :class:`~touchreal.server.settings.ServeSettings`' fields: ``--NAME`` for each (``_`` -> ``-``), each
also read from ``TOUCHREAL_<NAME>``; a flag given wins over the environment, which wins over the
default. Booleans are ``--NAME`` / ``--no-NAME``; lists are one comma-separated value.
"""

from __future__ import annotations

import argparse
import typing

from ..bridge import auth as nats_auth
from ..server.settings import ServeSettings


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="stream spikes over WebSockets (REST config, parameter uploads)",
                       description="Every flag also reads from the environment variable TOUCHREAL_<FLAG> "
                                   "(docs/service.md, Settings).")
    for name, field in ServeSettings.model_fields.items():
        env = f"TOUCHREAL_{name.upper()}"
        default = field.get_default(call_default_factory=True)
        shown = ",".join(map(str, default)) if isinstance(default, list) else default
        helptext = f"{field.description} ({env}; default {shown})".replace("%", "%%")
        if field.annotation is bool:
            p.add_argument(flag(name), action=argparse.BooleanOptionalAction, default=None, help=helptext)
        else:
            choices = typing.get_args(field.annotation) if typing.get_origin(field.annotation) is typing.Literal else None
            p.add_argument(flag(name), default=None, choices=choices, metavar=None if choices else name.upper(),
                           help=helptext)
    nats_auth.add_arguments(p)
    p.set_defaults(func=run)


def settings_from(args: argparse.Namespace) -> ServeSettings:
    """Flags given over the environment over the defaults (raises pydantic's ValidationError, a ValueError)."""
    return ServeSettings(**{k: v for k, v in vars(args).items() if k in ServeSettings.model_fields and v is not None})


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from ..redaction import redact
    from ..server.app import create_app, uvicorn_config
    from ..server.service import Service

    settings = settings_from(args)
    config = settings.runtime_config()
    service = Service(settings, config)
    companions = []
    if settings.publish:
        from ..bridge.publisher import NatsPublisher

        if not settings.sensor_id:
            raise ValueError("--publish needs --sensor-id (the NATS subjects are touchreal.<ID>.*)")
        companions.append(NatsPublisher(service, settings.publish, settings.sensor_id,
                                        publish_all=settings.publish_all, retain_s=settings.retain_s,
                                        auth=nats_auth.from_args(args)))
    app = create_app(service, companions)
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal {redact(config.source)} ({config.taxels} taxel(s)): dashboard http://{base}/ · "
          f"stream ws://{base}/v1/stream · API http://{base}/docs · state {settings.state_dir}"
          + (" · write endpoints need the token" if settings.token else "")
          + (f" · publishing to {redact(settings.publish)} as touchreal.{settings.sensor_id}.*" if settings.publish else ""),
          flush=True)
    uvicorn.Server(uvicorn_config(app, settings.host, settings.port, settings.log_level, settings)).run()
    return 0
