"""Simulated e-skin: real-time factor of the live scene source for 1, 16 and 64 taxels, and the large skin.

Streams the default scene (presses, vibration bursts, texture slides) in 32 ms chunks, as the
service does, and reports simulated seconds per wall-clock second (real-time factor, RTF) and per
CPU second of this process (less sensitive to other load on a shared machine).

Then the large-skin scene (``SimHops(..., touched=f)``) for ``--large`` taxel counts (4096, 16,384,
65,536) at ``--touched`` fractions (1 %, 5 %): process CPU time per hop against the hop's duration
(5 and 32 ms hops), the taxels whose contact physics runs, and the resident memory of the simulation
(RSS of this whole process after each run); the CPU is named.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per taxel count (default 20)")
    parser.add_argument("--chunk-ms", type=float, default=32.0, help="read size (ms, default 32)")
    parser.add_argument("--taxels", type=int, nargs="+", default=[1, 16, 64], help="taxel counts (default 1 16 64)")
    parser.add_argument("--large", type=int, nargs="*", default=[4096, 16384, 65536],
                        help="large-skin taxel counts (default 4096 16384 65536; none: skip)")
    parser.add_argument("--touched", type=float, nargs="+", default=[0.01, 0.05],
                        help="touched fractions of the large skin (default 0.01 0.05)")
    parser.add_argument("--large-seconds", type=float, default=4.0, help="simulated seconds per large-skin run (default 4)")


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
    if args.large:
        large(args.large, args.touched, args.large_seconds)
    return 0


def _rss_mib() -> float:
    """This process's resident memory now (MiB; Linux /proc)."""
    import os

    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def large(counts: list[int], fractions: list[float], seconds: float) -> None:
    """CPU per hop of the large-skin scene against real time, per taxel count, touched fraction and hop."""
    from touchreal.sources.live import SimHops

    from .skin import cpu_name

    SimHops(64, 0.005, touched=0.05).read_hop()  # compile the kernels
    print(f"\nlarge skin ({cpu_name()}, one thread; process CPU per hop after 1.5 s of warm-up, {seconds:g} s each)")
    print(f"{'taxels':>6} {'touched':>7} {'hop ms':>6} {'cpu ms/hop':>10} {'p99 ms':>7} {'x real time':>11} "
          f"{'physics on':>10} {'RSS MiB':>8}")
    for n in counts:
        for f in fractions:
            for hop_s in (0.005, 0.032):
                sim = SimHops(n, hop_s, seed=1, touched=f)
                while sim.scene.time_s - sim.zero_s < 1.5:  # past the landing, the active set at its typical size
                    sim.read_hop()
                cost, on = [], []
                for _ in range(max(int(seconds / hop_s), 1)):
                    c = time.process_time()
                    sim.read_hop()
                    cost.append(time.process_time() - c)
                    on.append(sim.scene.active.size / n)
                ms = 1000 * np.array(cost)
                print(f"{n:6d} {100 * f:6.0f}% {hop_s * 1000:6.0f} {ms.mean():10.2f} {np.percentile(ms, 99):7.2f} "
                      f"{ms.mean() / (hop_s * 1000):11.2f} {100 * np.mean(on):9.1f}% {_rss_mib():8.0f}")
                del sim
