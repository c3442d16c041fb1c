"""``touchreal serve``: the service on a source (the simulated e-skin by default).

Its flags are :class:`~touchreal.server.settings.ServeSettings`' fields and, for ``--publish``,
:class:`~touchreal.bridge.auth.NatsAuth`'s as ``--nats-*`` (:mod:`.flags`: flag over environment over
default).
"""

from __future__ import annotations

import argparse

from ..server.settings import ServeSettings
from .flags import add_server_parser, model_from_args, nats_auth_from_args


def register(sub: argparse._SubParsersAction) -> None:
    add_server_parser(sub, "serve", ServeSettings, run,
                      help="stream spikes over WebSockets (REST config, parameter uploads)",
                      description="Every flag also reads from the environment variable TOUCHREAL_<FLAG> "
                                  "(docs/service.md, Settings).")


def settings_from(args: argparse.Namespace) -> ServeSettings:
    """Flags given over the environment over the defaults (raises pydantic's ValidationError, a ValueError)."""
    return model_from_args(ServeSettings, args)


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
                                        auth=nats_auth_from_args(args)))
    app = create_app(service, companions)
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal {redact(config.source)} ({config.taxels} taxel(s)): dashboard http://{base}/ · "
          f"stream ws://{base}/v1/stream · API http://{base}/docs · state {settings.state_dir}"
          + (" · write endpoints need the token" if settings.token else "")
          + (f" · publishing to {redact(settings.publish)} as touchreal.{settings.sensor_id}.*" if settings.publish else ""),
          flush=True)
    uvicorn.Server(uvicorn_config(app, settings.host, settings.port, settings.log_level)).run()
    return 0
