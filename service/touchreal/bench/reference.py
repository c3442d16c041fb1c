"""Reference model: time to simulate the 17 TouchSim models for a 1 s single-probe stimulus.

Times ``touchreal.reference.model.reference_trains`` (mechanics + input stage + LIF, all 17 models,
one afferent location) on a 5 kHz stimulus of ``--duration`` seconds, noiseless and noisy, after a
warm-up call (numba compilation is cached on disk and excluded). Prints mean / median over
``--repeats`` timed calls and the speed relative to real time (stimulus duration / compute time).

TouchSim itself (python package ``touchsim`` 0.1.1) is not installable here (not on PyPI), so no
TouchSim figure is measured or printed; see docs/reference-model.md for what is known of its cost.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

STIMULI = ("sine", "ramp", "noise")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per configuration (default 30)")
    parser.add_argument("--duration", type=float, default=1.0, help="stimulus duration in s (default 1.0)")
    parser.add_argument("--stimulus", choices=STIMULI, default="sine",
                        help="sine: 0.5 mm + 0.1 mm at 100 Hz; ramp: 1 mm ramp-hold-release; noise: 0.3 mm + "
                             "band-limited noise (default sine)")
    parser.add_argument("--trains", type=int, default=1,
                        help="noisy repeats computed per call (the noisy figure; default 1)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")


def make_stimulus(kind: str, duration_s: float, fs_hz: float = 5000.0, seed: int = 0) -> np.ndarray:
    """A benchmark indentation trace (mm) at ``fs_hz``."""
    n = max(2, int(round(duration_s * fs_hz)))
    t = np.arange(n) / fs_hz
    if kind == "sine":
        return 0.5 + 0.1 * np.sin(2 * np.pi * 100.0 * t)
    if kind == "ramp":
        rise = min(0.1, duration_s / 4)
        return np.clip(np.minimum(t / rise, (duration_s - t) / rise), 0.0, 1.0)
    if kind == "noise":
        from scipy import signal

        b, a = signal.butter(4, 500.0 / (fs_hz / 2))
        z = signal.lfilter(b, a, np.random.default_rng(seed).standard_normal(n))
        return 0.3 + 0.01 * z / z.std()
    raise ValueError(f"unknown stimulus {kind!r}")


def _time(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def run(args: argparse.Namespace) -> int:
    from ..reference.model import reference_trains

    if args.repeats < 1 or args.trains < 1 or not args.duration > 0:
        raise ValueError("--repeats and --trains must be >= 1 and --duration > 0")
    trace = make_stimulus(args.stimulus, args.duration, seed=args.seed)
    configs = [
        ("noiseless", dict(noisy=False, repeats=1)),
        (f"noisy x{args.trains}", dict(noisy=True, repeats=args.trains)),
    ]
    print(f"reference model: 17 models, 1 location, {args.stimulus} stimulus of {args.duration:g} s at 5 kHz "
          f"({trace.size} samples), {args.repeats} timed calls each")
    for name, kw in configs:
        res = reference_trains(trace, seed=args.seed, **kw)  # warm-up (numba cache load, filter design)
        n_spikes = sum(int(r.t.size) for r in res.values())
        times = _time(lambda: reference_trains(trace, seed=args.seed, **kw), args.repeats)
        mean, med = statistics.fmean(times), statistics.median(times)
        print(f"  {name:12s} mean {mean * 1e3:8.2f} ms  median {med * 1e3:8.2f} ms  "
              f"min {min(times) * 1e3:8.2f} ms  = {args.duration / med:7.1f}x real time  ({n_spikes} spikes)")
    print("TouchSim (touchsim 0.1.1): not measured here (not installable: not on PyPI); see docs/reference-model.md")
    return 0
