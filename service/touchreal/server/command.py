"""``touchreal serve``: the service on a source (the simulated e-skin by default)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="stream spikes over WebSockets (REST config, parameter uploads)")
    p.add_argument("--source", default="sim", help="sim | replay:DATASET_DIR[:TRIAL_ID,...] | serial:PORT (default sim)")
    p.add_argument("--taxels", type=int, default=1, help="taxels of the simulated e-skin / serial device")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed (x real time)")
    p.add_argument("--loop", action="store_true", help="replay: start again after the last trial")
    p.add_argument("--host", default=None, help="bind address (default 127.0.0.1; TOUCHREAL_HOST)")
    p.add_argument("--port", type=int, default=None, help="port (default 8765; TOUCHREAL_PORT)")
    p.add_argument("--token", default=None, help="bearer token for write endpoints (or TOUCHREAL_TOKEN)")
    p.add_argument("--state-dir", type=Path, default=None, help="parameter history + user models (TOUCHREAL_STATE_DIR)")
    p.add_argument("--params", type=Path, default=None, help="initial parameter file (default: last active, else shipped)")
    p.add_argument("--taxel-block", type=int, default=None,
                   help="taxels per preprocessing block; blocks nobody subscribes to run nothing (default 64; 0 = one "
                        "block; TOUCHREAL_TAXEL_BLOCK)")
    p.add_argument("--hop-ms", type=float, default=None,
                   help="hop (ms): how often the source hands over samples and the fast classes go out (default 5; "
                        "at most update_ms; TOUCHREAL_HOP_MS)")
    p.add_argument("--log-level", default="warning", help="uvicorn log level")
    p.add_argument("--publish", default=None, metavar="NATS_URL",
                   help="also publish the frames to NATS (docs/scale-out.md), e.g. nats://127.0.0.1:4222")
    p.add_argument("--sensor-id", default=None, help="with --publish: subjects touchreal.<ID>.frames/.hello/.demand")
    p.add_argument("--publish-all", action="store_true",
                   help="with --publish: every class and taxel, whatever the gateways forward as demand")
    p.add_argument("--retain-s", type=float, default=0.0, metavar="S",
                   help="with --publish: keep the last S seconds of published frames in an in-memory JetStream "
                        "stream touchreal_<ID> for late joiners (nats-server -js)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from .app import create_app, uvicorn_config
    from .service import Service
    from .settings import RuntimeConfig, ServeSettings

    overrides = {k: v for k, v in (("host", args.host), ("port", args.port), ("token", args.token),
                                   ("state_dir", args.state_dir), ("params", args.params),
                                   ("taxel_block", args.taxel_block), ("hop_ms", args.hop_ms)) if v is not None}
    settings = ServeSettings(**overrides)
    config = RuntimeConfig(source=args.source, taxels=args.taxels, speed=args.speed, loop=args.loop)
    service = Service(settings, config)
    companions = []
    if args.publish:
        from ..bridge.publisher import NatsPublisher

        if not args.sensor_id:
            raise ValueError("--publish needs --sensor-id (the NATS subjects are touchreal.<ID>.*)")
        companions.append(NatsPublisher(service, args.publish, args.sensor_id, publish_all=args.publish_all,
                                        retain_s=args.retain_s))
    app = create_app(service, companions)
    base = f"{settings.host}:{settings.port}"
    print(f"TouchReal {config.source} ({config.taxels} taxel(s)): dashboard http://{base}/ · "
          f"stream ws://{base}/v1/stream · API http://{base}/docs · state {settings.state_dir}"
          + (" · write endpoints need the token" if settings.token else "")
          + (f" · publishing to {args.publish} as touchreal.{args.sensor_id}.*" if args.publish else ""), flush=True)
    uvicorn.Server(uvicorn_config(app, settings.host, settings.port, args.log_level)).run()
    return 0
