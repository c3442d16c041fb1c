"""``touchreal bridge {foxglove,lsl,ros2} --from URL``: a live stream into Foxglove, Lab Streaming
Layer or ROS 2.

The bridges live in the client package (``touchreal_client.bridges``, extras ``[foxglove]``,
``[lsl]`` and ``[ros2]``); this module only parses the command line and runs one until Ctrl-C
(docs/ecosystem.md).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys

from touchreal_client.errors import TouchRealError

DEFAULT_FROM = "ws://127.0.0.1:8765/v1/stream"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bridge", help="bridge a live /v1/stream into Foxglove, Lab Streaming Layer or ROS 2")
    kinds = p.add_subparsers(dest="bridge", required=True, metavar="KIND")
    fox = kinds.add_parser("foxglove", help="serve the Foxglove WebSocket protocol (open ws://HOST:PORT in Foxglove)")
    fox.add_argument("--from", dest="url", default=DEFAULT_FROM, help=f"a service's or gateway's stream (default {DEFAULT_FROM})")
    fox.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    fox.add_argument("--port", type=int, default=8767, help="Foxglove WebSocket port (default 8767)")
    fox.add_argument("--decimation", type=int, default=25, help="channels: one 5 kHz sample in N (default 25 = 200 Hz)")
    fox.set_defaults(func=run_foxglove)
    lsl = kinds.add_parser("lsl", help="LSL outlets: spikes (irregular rate) and force/channels (regular)")
    lsl.add_argument("--from", dest="url", default=DEFAULT_FROM, help=f"a service's or gateway's stream (default {DEFAULT_FROM})")
    lsl.add_argument("--name", default="TouchReal", help="stream name prefix (default TouchReal)")
    lsl.add_argument("--decimation", type=int, default=25, help="channels: one 5 kHz sample in N (default 25 = 200 Hz)")
    lsl.set_defaults(func=run_lsl)
    ros = kinds.add_parser("ros2", help="ROS 2 topics over DDS (ros2 topic list / echo on the same ROS_DOMAIN_ID)")
    ros.add_argument("--from", dest="url", default=DEFAULT_FROM, help=f"a service's or gateway's stream (default {DEFAULT_FROM})")
    ros.add_argument("--domain-id", type=int, default=None,
                     help="DDS domain, as ROS_DOMAIN_ID (default: the ROS_DOMAIN_ID environment variable, else 0)")
    ros.add_argument("--decimation", type=int, default=25, help="channels: one 5 kHz sample in N (default 25 = 200 Hz)")
    ros.set_defaults(func=run_ros2)


def _check_decimation(n: int) -> None:
    if not 1 <= n <= 5000:
        raise ValueError(f"--decimation must be in 1..5000, got {n}")


def _serve(bridge, describe) -> int:
    """Run ``bridge`` until SIGINT/SIGTERM (or until its stream ends); print ``describe()`` once it
    is ready. A signal cancels the bridge, which closes its server or outlets and its stream."""

    async def main() -> None:
        task = asyncio.create_task(bridge.run())
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        ready = asyncio.create_task(bridge.ready.wait())
        await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
        if ready.done():
            print(describe(), flush=True)
        else:
            ready.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    try:
        asyncio.run(main())
    except TouchRealError as exc:  # cannot reach the stream, or it ended for good: a clear message, no traceback
        print(f"touchreal bridge: error: {exc}", file=sys.stderr)
        return 2
    return 0


def run_foxglove(args: argparse.Namespace) -> int:
    from touchreal_client.bridges.foxglove import FoxgloveBridge

    _check_decimation(args.decimation)
    bridge = FoxgloveBridge(args.url, host=args.host, port=args.port, decimation=args.decimation)
    return _serve(bridge, lambda: f"Foxglove WebSocket on ws://{args.host}:{bridge.port} from {args.url} "
                                  "(Foxglove: Open connection -> Foxglove WebSocket)")


def run_lsl(args: argparse.Namespace) -> int:
    from touchreal_client.bridges.lsl import LslBridge

    _check_decimation(args.decimation)
    bridge = LslBridge(args.url, name=args.name, decimation=args.decimation)
    return _serve(bridge, lambda: f"LSL outlets {', '.join(bridge.outlet_names)} from {args.url}")


def run_ros2(args: argparse.Namespace) -> int:
    from touchreal_client.bridges.ros2 import Ros2Bridge, default_domain_id

    _check_decimation(args.decimation)
    domain = default_domain_id() if args.domain_id is None else args.domain_id
    bridge = Ros2Bridge(args.url, domain_id=domain, decimation=args.decimation)
    return _serve(bridge, lambda: f"ROS 2 topics on DDS domain {domain} from {args.url}: {', '.join(bridge.topics)} "
                                  "(ros2 topic list; ros2 topic echo /touchreal/spikes/SA1)")
