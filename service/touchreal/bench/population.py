"""Afferent populations: encoder CPU time per second of signal for a fingertip patch, beside one afferent per taxel and class.

A ``--side`` x ``--side`` patch of ``--pitch`` mm (default 4 x 4 at 3 and 5 mm) carries a
population at the fingertip densities (default plan, variants of gain 1: the cost does not depend
on the gains). The simulated patch records a probe that presses and vibrates (the validation's fast burst) at a
taxel's centre (``--seconds`` of signal); the recording is then fed to the stream encoder in 32 ms chunks, as the
service does, with every afferent subscribed. Reported: the encoder's process CPU seconds per
second of signal (below 2 on this 2-core machine is real time; below 1 leaves a core), beside the
taxel encoder on the same recording in the same run, and the CPU's name.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pitch", type=float, nargs="+", default=[3.0, 5.0], help="taxel pitches in mm (default 3 5)")
    parser.add_argument("--side", type=int, default=4, help="taxels per side (default 4)")
    parser.add_argument("--seconds", type=float, default=6.0, help="seconds of signal per run (default 6)")


def _cpu_per_s(params, raw, n_taxels: int, population, seconds: float) -> float:
    from touchreal.stream import StreamEncoder

    se = StreamEncoder(params, n_taxels, update_s=0.032, population=population)
    c0 = time.process_time()
    step = 0.032
    for a in np.arange(0.0, seconds, step):
        st, pv = (raw.st_t >= a) & (raw.st_t < a + step), (raw.pvdf_t >= a) & (raw.pvdf_t < a + step)
        se.process(type(raw)(raw.st_t[st], raw.st[st], raw.pvdf_t[pv], raw.pvdf[pv]))
    return (time.process_time() - c0) / seconds


def run(args: argparse.Namespace) -> int:
    from touchreal.analysis.population import FAST_HZ
    from touchreal.bench.skin import cpu_name
    from touchreal.params import default_params
    from touchreal.population.encoder import Population
    from touchreal.population.layout import PopulationPlan
    from touchreal.simulator.patch import grid_patch, patch_skin
    from touchreal.simulator.scene import Scene, SceneEvent, SceneSource
    from touchreal.simulator.stimuli import RampHold, SineBurst

    params = default_params()
    print(f"CPU: {cpu_name()}; {args.side} x {args.side} taxels, {args.seconds:g} s of signal, 32 ms chunks")
    print(f"{'pitch mm':>8} {'afferents':>9} {'CPU s/s population':>19} {'CPU s/s taxels':>15} {'ratio':>6}")
    for pitch in args.pitch:
        taxels = grid_patch(args.side, pitch)
        skin = patch_skin(pitch)
        centre = (float(taxels[0, 0]), float(taxels[0, 1]))
        scene = Scene((SceneEvent(0.3, RampHold(1.0, 20.0, 20.0, 1.0), centre),
                       SceneEvent(2.0, SineBurst.calibrated(FAST_HZ, skin, resting=False), centre)), loop_s=3.5)
        raw = SceneSource(scene, taxels_xy_mm=taxels, seed=0, skin=skin, t0_s=0.0).read(args.seconds + 0.1)
        pop = Population.build(taxels, PopulationPlan())
        _cpu_per_s(params, raw, len(taxels), pop, 0.5)  # compile and warm every kernel
        ours = _cpu_per_s(params, raw, len(taxels), pop, args.seconds)
        base = _cpu_per_s(params, raw, len(taxels), None, args.seconds)
        print(f"{pitch:>8g} {len(pop):>9d} {ours:>19.3f} {base:>15.3f} {ours / base:>6.1f}")
    return 0
