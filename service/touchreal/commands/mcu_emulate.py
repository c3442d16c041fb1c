"""``touchreal mcu-emulate DATASET_DIR --port PATH``: a recording played as the microcontroller would.

Creates a pseudo-terminal, links PATH to it and streams the trials as serial frames
(docs/serial-protocol.md), so ``touchreal serve --source serial:PATH`` can be tried without
hardware. Prints PATH once the port exists, and the device's counters at the end. With
``--truth FILE`` it writes, per frame, the device time of its newest sample and the host wall time
at which that sample was acquired (CSV ``device_us,wall_us``), the truth a host's clock estimate is
checked against.
"""

from __future__ import annotations

import argparse
import itertools
import json
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from ..recording import Dataset
from ..device.mcu_emulator import Faults, Link, PtyPort, frame_schedule, play
from ..device.serial_frame import MAX_TAXELS, MAX_VALUES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mcu-emulate", help="play a recording over a pseudo-terminal like the sensor microcontroller")
    p.add_argument("dataset", type=Path, help="dataset folder (manifest.json + trials/)")
    p.add_argument("--port", type=Path, required=True, help="symlink to create for the emulated port, e.g. /tmp/ttyTR0")
    p.add_argument("--trial", nargs="+", action="extend", default=None, metavar="ID", help="trials to play (default all)")
    p.add_argument("--loop", action="store_true", help="start over after the last trial, forever")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed relative to real time (default 1)")
    p.add_argument("--taxels", type=int, default=1, help="taxels per frame; each carries the recording (default 1)")
    p.add_argument("--pvdf-block", type=int, default=10, help="PVDF samples per frame (default 10 = 5 ms)")
    p.add_argument("--corrupt-rate", type=float, default=0.0, help="probability a frame gets one byte flipped")
    p.add_argument("--drop-rate", type=float, default=0.0, help="probability a frame is lost")
    p.add_argument("--unplug-after", type=float, default=None, metavar="S", help="unplug after S s of playback")
    p.add_argument("--replug-after", type=float, default=1.0, metavar="S", help="replug S s after an unplug (default 1)")
    p.add_argument(
        "--wait-for-host", type=float, default=0.0, metavar="S", help="hold the start until a host opens the port (at most S s)"
    )
    p.add_argument("--clock-drift-ppm", type=float, default=0.0, metavar="PPM",
                   help="the device clock runs PPM fast (negative: slow) against the host's (default 0)")
    p.add_argument("--jitter-ms", type=float, default=0.0, metavar="MEAN",
                   help="frames leave MEAN ms late on average (exponential), and about once a second the link "
                   "stalls for 10 x MEAN ms (default 0)")
    p.add_argument("--truth", type=Path, default=None, metavar="FILE",
                   help="write device_us,wall_us per frame: when its newest sample was acquired (CSV)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault and jitter generators and the session id")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    ds = Dataset.open(args.dataset)
    try:
        entries = [ds.entry(t) for t in args.trial] if args.trial else ds.trials
    except KeyError as exc:
        raise ValueError(f"{args.dataset}: no trial {exc.args[0]!r}") from None
    if not (1 <= args.taxels <= MAX_TAXELS and 1 <= args.pvdf_block and args.taxels * args.pvdf_block <= MAX_VALUES):
        raise ValueError(f"--taxels (1..{MAX_TAXELS}) times --pvdf-block must be at most {MAX_VALUES} values per frame")
    faults = Faults(drop_rate=args.drop_rate, corrupt_rate=args.corrupt_rate, seed=args.seed)
    link = Link(drift_ppm=args.clock_drift_ppm, jitter_ms=args.jitter_ms, seed=args.seed)
    trials = (ds.load(e) for e in (itertools.cycle(entries) if args.loop else entries))
    schedule = frame_schedule(trials, n_taxels=args.taxels, pvdf_block=args.pvdf_block, faults=faults)
    port = PtyPort(args.port)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    truth = args.truth.open("w", buffering=1) if args.truth is not None else None
    try:
        port.plug()
        print(args.port, flush=True)
        stats = play(
            schedule,
            port,
            speed=args.speed,
            unplug_after_s=args.unplug_after,
            replug_after_s=args.replug_after,
            wait_for_host_s=args.wait_for_host,
            should_stop=stop.is_set,
            link=link,
            on_acquired=_truth_writer(truth) if truth is not None else lambda device_us, mono_s: None,
        )
    except KeyboardInterrupt:
        stats = port.stats
    finally:
        port.close()
        if truth is not None:
            truth.close()
    print(json.dumps(stats.as_dict()), flush=True)
    return 0


def _truth_writer(out: TextIO) -> Callable[[int, float], None]:
    """Writes ``device_us,wall_us`` lines: the host monotonic time moved onto the wall clock."""
    out.write("device_us,wall_us\n")

    def write(device_us: int, mono_s: float) -> None:
        wall_minus_mono_us = (time.time_ns() - time.monotonic_ns()) // 1000
        out.write(f"{device_us},{round(mono_s * 1e6) + wall_minus_mono_us}\n")

    return write
