"""Simulated e-skin: real-time factor of the live scene source for 1, 16 and 64 taxels.

Streams the default scene (presses, vibration bursts, texture slides) in 32 ms chunks, as the
service does, and reports simulated seconds per wall-clock second (real-time factor, RTF) and per
CPU second of this process (less sensitive to other load on a shared machine).
"""

from __future__ import annotations

import argparse
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per taxel count (default 20)")
    parser.add_argument("--chunk-ms", type=float, default=32.0, help="read size (ms, default 32)")
    parser.add_argument("--taxels", type=int, nargs="+", default=[1, 16, 64], help="taxel counts (default 1 16 64)")


def run(args: argparse.Namespace) -> int:
    from touchreal.raw import taxel_grid
    from touchreal.simulator.scene import SceneSource, default_scene

    warm = SceneSource(seed=0)  # load/compile every kernel and code path once (one loop of the scene)
    for _ in range(int((warm.scene.loop_s or 20.0) / 0.032) + 1):
        warm.read(0.032)
    print(f"{'taxels':>6} {'chunk ms':>8} {'sim s':>6} {'wall s':>7} {'RTF':>8} {'CPU s':>7} {'RTF(CPU)':>9}")
    for n in args.taxels:
        xy = taxel_grid(n, 10.0)
        src = SceneSource(default_scene(positions_mm=[xy[0], (0.0, 0.0)]), taxels_xy_mm=xy, seed=1)
        chunk = args.chunk_ms / 1000.0
        src.read(1.0)  # warm-up: caches, first blocks of noise
        steps = max(int(round(args.seconds / chunk)), 1)
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(steps):
            src.read(chunk)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        sim = steps * chunk
        print(f"{n:>6d} {args.chunk_ms:>8.1f} {sim:>6.1f} {wall:>7.3f} {sim / wall:>8.1f} {cpu:>7.3f} {sim / cpu:>9.1f}")
    return 0
