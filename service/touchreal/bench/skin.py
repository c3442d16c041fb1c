"""Large skins (``touchreal bench encoder --skin``): activity-driven compute against the dense chain,
side by side in one run, on the simulated e-skin's large-skin scene (sparse moving contacts over a
grid; the untouched taxels read the build's noise, hum and drift).

Every figure is the encoder's process CPU time (all threads) per second of signal on the service's
5 ms hop, the simulation's own CPU time excluded (measured around it and subtracted), after a
warm-up past the stream start. Ratios are against the dense 4096-taxel figure of the same run and
dtype (the mean of its runs at 0, 5 and 100 % touched: its compute does not depend on the contacts,
and three runs average out a run's noise), so they hold across machines; the CPU is named beside the absolute figures.

* fraction sweep: 4096 taxels, touched fraction 0 / 1 / 5 / 25 / 100 % activity-driven, beside
  dense at 0, 5 and 100 % (dense compute does not depend on the contacts; every taxel in one block,
  the fastest dense chain), float64 and float32;
* scale: 16,384 taxels at 1 % and 5 %, 65,536 at 1 % (activity-driven);
* idle cost: an idle taxel's cost as a fraction of a touched one's (sparse at 0 % against the dense reference);
* agreement: per class, the spike count difference and the van Rossum distance (10 ms) between the
  activity-driven and the dense spikes of the 4096-taxel 5 % run, and the spikes on taxels the
  dense run left silent;
* memory: the process's peak RSS per taxel after the 65,536-taxel run.
"""

from __future__ import annotations

import platform
import resource
import time
from collections.abc import Iterator

import numpy as np

from ..analysis.spiketrains import vr_distance
from ..encoding.encoder import SpikeEvents
from ..params import EncoderParams
from ..preprocess.activity import ActivityPlan
from ..raw import RawChunk
from ..settings import CLASSES
from ..sources.live import SimHops
from ..stream import StreamEncoder

HOP_S = 0.005  #: the service's hop
WARM_S = 1.5  #: past the stream start and the detector's learning (its noise scale, ``noise_tau_s`` / 2)
FRACTIONS = (0.0, 0.01, 0.05, 0.25, 1.0)


def cpu_name() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else the platform's processor string."""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _hops(n: int, touched: float, seconds: float, seed: int = 0) -> Iterator[tuple[RawChunk, float]]:
    """(hop, CPU seconds its simulation took) for ``seconds`` of the large-skin scene."""
    sim = SimHops(n, HOP_S, seed=seed, touched=touched)
    for _ in range(int(round(seconds / HOP_S))):
        t = time.process_time()
        hop = sim.read_hop()
        yield hop, time.process_time() - t


def run_skin(params: EncoderParams, n: int, touched: float, seconds: float, dtype: type, sparse: bool,
             keep: bool = False) -> tuple[float, float, SpikeEvents | None]:
    """(encoder CPU s per s of signal, mean fraction of taxels awake, the spikes if ``keep``); dense:
    every taxel in one block (the fastest dense chain)."""
    se = StreamEncoder(params, n, dtype=dtype, update_s=params.preprocess.update_ms / 1000.0,
                       activity=ActivityPlan() if sparse else None)
    se.set_active({c: range(n) for c in se.classes})  # every column's spikes, no channels (as a spikes subscriber)
    parts, cpu, sim_cpu, signal, awake = [], 0.0, 0.0, 0.0, []
    for i, (hop, sim_s) in enumerate(_hops(n, touched, seconds + WARM_S)):
        t = time.process_time()
        ev = se.process(hop)
        spent = time.process_time() - t
        if keep:
            parts.append(ev)
        if i * HOP_S >= WARM_S:
            cpu += spent
            sim_cpu += sim_s
            signal += HOP_S
            awake.append(se.awake_taxels / n)
    if keep:
        parts.append(se.finish())
    return cpu / signal, float(np.mean(awake)), SpikeEvents.concatenate(parts) if keep else None


def _trains(ev: SpikeEvents, ci: int) -> dict[int, np.ndarray]:
    """Class ``ci``'s sorted spike times per taxel."""
    sel = ev.cls == ci
    taxel, t = ev.taxel[sel], ev.t_s[sel]
    order = np.lexsort((t, taxel))
    taxel, t = taxel[order], t[order]
    keys, starts = np.unique(taxel, return_index=True)
    return {int(k): a for k, a in zip(keys, np.split(t, starts[1:]))}


def agreement(dense: SpikeEvents, sparse: SpikeEvents) -> None:
    """Per class: spike counts, their difference, the mean and largest VR distance (10 ms) over taxels
    with spikes, and spikes on taxels the dense run left silent."""
    print(f"{'class':>5} {'dense':>8} {'sparse':>8} {'diff %':>7} {'VR mean':>8} {'VR max':>7} {'extra':>6}")
    for ci, c in enumerate(CLASSES):
        d, s = _trains(dense, ci), _trains(sparse, ci)
        nd, ns = sum(a.size for a in d.values()), sum(a.size for a in s.values())
        empty = np.zeros(0)
        vr = [vr_distance(d.get(k, empty), s.get(k, empty), 0.01, presorted=True) for k in set(d) | set(s)] or [0.0]
        extra = sum(a.size for k, a in s.items() if k not in d)
        print(f"{c:>5} {nd:8d} {ns:8d} {100 * (ns - nd) / max(nd, 1):7.2f} {np.mean(vr):8.3f} {np.max(vr):7.3f} {extra:6d}")


def skin(params: EncoderParams, seconds: float) -> None:
    print(f"\n== large skins: activity-driven against dense ({cpu_name()}; encoder process CPU per second of signal, "
          f"5 ms hop, {seconds:g} s after {WARM_S:g} s of warm-up; ratios against dense 4096, the mean of its 0, 5 and 100 % runs)")
    print(f"{'taxels':>6} {'touched':>7} {'dtype':>7} {'compute':>7} {'awake':>6} {'ms per s':>9} {'x dense 4096':>12}")
    dense_ref, rows, spikes = {}, [], {}

    def show(n: int, f: float, name: str, sparse: bool, awake: float, per_s: float) -> None:
        print(f"{n:6d} {100 * f:6.0f}% {name:>7} {'sparse' if sparse else 'dense':>7} "
              f"{100 * awake:5.1f}% {per_s * 1000:9.1f} {per_s / dense_ref[name]:12.3f}", flush=True)

    def row(n: int, f: float, dtype: type, sparse: bool, keep: bool = False) -> tuple:
        per_s, awake, ev = run_skin(params, n, f, seconds, dtype, sparse, keep)
        if keep:
            spikes[sparse] = ev
        rows.append((n, f, np.dtype(dtype).name, sparse, awake, per_s))
        return rows[-1]

    for dtype in (np.float64, np.float32):
        name = np.dtype(dtype).name
        dense = [row(4096, f, dtype, False, keep=dtype is np.float64 and f == 0.05) for f in (0.0, 0.05, 1.0)]
        dense_ref[name] = float(np.mean([r[-1] for r in dense]))  # dense compute does not depend on the contacts
        for r in dense:
            show(*r)
        show(*row(4096, 0.05, dtype, True, keep=dtype is np.float64))
        for f in FRACTIONS:
            if f != 0.05:
                show(*row(4096, f, dtype, True))
        for n, f in ((16384, 0.01), (16384, 0.05), (65536, 0.01)):
            show(*row(n, f, dtype, True))
    for name in dense_ref:
        by = {(n, f, s): p for n, f, nm, s, _, p in rows if nm == name}
        print(f"{name}: idle taxel / touched taxel (sparse 0 % / dense, 4096): {by[(4096, 0.0, True)] / dense_ref[name]:.3f}")
    print("\nagreement, 4096 taxels at 5 % touched, float64 (activity-driven against dense):")
    agreement(spikes[False], spikes[True])
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"\npeak RSS after the 65,536-taxel runs: {rss / 2**20:.0f} MiB, {rss / 65536 / 1024:.1f} KiB per taxel")
