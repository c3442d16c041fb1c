"""``touchreal record URL --out FILE.mcap [--seconds S] [--streams spikes,channels,decoded]``.

Records a running service's (or gateway's) stream into MCAP with
:func:`touchreal_client.record.record` (docs/ecosystem.md, "Files").
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record a live stream (spikes, channels, decoded outputs) into an MCAP file")
    p.add_argument("url", help="the service or gateway: http://HOST:PORT or ws://HOST:PORT/v1/stream")
    p.add_argument("--out", type=Path, required=True, help="the .mcap file to write")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C or the stream ends)")
    p.add_argument("--streams", default="spikes,channels,decoded", help="comma list of spikes, channels, decoded")
    p.add_argument("--decimation", type=int, default=25, help="channels: one 5 kHz sample in this many (25 -> 200 Hz)")
    p.add_argument("--taxels", default=None, help="comma list of taxel ids (default: all)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from touchreal_client import TouchRealError

    try:
        from touchreal_client.record import record
    except ModuleNotFoundError as exc:
        raise ValueError(f"needs the mcap extra: pip install 'touchreal-client[mcap]' ({exc})") from exc

    if args.seconds is not None and not args.seconds > 0:
        raise ValueError("--seconds must be > 0")
    taxels = [int(t) for t in args.taxels.split(",")] if args.taxels else None
    streams = tuple(s.strip() for s in args.streams.split(",") if s.strip())
    try:
        summary = asyncio.run(record(args.url, args.out, seconds=args.seconds, streams=streams,
                                     decimation=args.decimation, taxels=taxels))
    except KeyboardInterrupt:
        print(f"interrupted; {args.out} is complete up to here")
        return 0
    except TouchRealError as exc:  # the service is unreachable, refused the subscription, ...
        print(f"touchreal record: error: {exc}", file=sys.stderr)
        return 2
    c = summary.counts
    print(f"{summary.path}: {c['spikes']} spikes, {c['channel_samples']} channel samples, {c['decoded_steps']} decoded steps, "
          f"{c['clock_points']} clock points, params revs {summary.params_revs}; stopped: {summary.stop_reason}"
          + (f"; {summary.missed_frames} frames dropped by the server" if summary.missed_frames else ""))
    return 0
