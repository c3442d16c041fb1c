"""Encoder benchmark: compute time per update, per-class latency, and run time against error per window.

Part 1 drives the full online chain (preprocessing + LIF, all three classes) with the simulated
e-skin's live scene for 1, 16 and 256 taxels (``--taxels``, up to 4096) in 32 ms updates and reports
the compute time per update (mean, p95, p99, max), the process CPU time per update (all threads)
and the real-time factor (update interval / mean compute time), in float64 and in float32
preprocessing, and float64 on one thread with the threads' speed-up.

Part 1b compares the compute per second of sensor time of the service's hop (5 ms chunks: the
SingleTact-only and short-window sources every hop, the 128 ms window on the 32 ms update) with
32 ms updates (every source every update), at 1 taxel and the ``--taxels`` counts up to 1024, in the
service's blocks of 64 taxels and in one block, as CPU time of the process, all threads (the best of three runs of each, interleaved): the
cost of the short hop is per-call overhead.

Part 1c is the service's own budget without the network: the simulated e-skin chunked as ``touchreal
serve`` chunks it (hops ending right after the SingleTact samples), and per class the spike's
emission (its chunk's newest sample + the compute of that call) minus the sensor time of its causing
sample (stamp minus the class delay), p50/p95/max, on the 5 ms hop and on 32 ms updates.

Part 2 measures each class's latency: the live scene fed in 1 ms chunks, every spike's emission
(the newest sample time of the chunk that returned it) minus its stamp, on the sensor clock, with
the class's ``delay_ms`` (raw) and without it (the pipeline's own latency), next to the algorithmic
bound (``StreamEncoder.latency_s``), for the parameter file's windows and per-class window sets.

Part 3 encodes ramp and sine trials with causal windows of 16-512 ms (all classes on one window, and
per-class window sets) and reports, against the 128 ms / float64 result, the mean absolute
spike-count error (%) and the mean van Rossum distance (tau 10 ms), with the compute time per update
for one taxel. It uses rig-v1 from TOUCHREAL_SHARED when present, otherwise a small simulated dataset.

``--skin`` runs only the large-skin part instead (bench/skin.py): activity-driven against dense
compute from 4096 to 65,536 taxels, side by side.

Part 4 soaks the chain with a long simulated stream (``--soak-hours``) and reports the largest
state magnitude, the state size at the start and end (flat memory) and the process RSS.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from ..analysis.spiketrains import vr_distance
from ..params import EncoderParams, default_params
from ..preprocess import parallel
from ..recording import Dataset
from ..raw import RawChunk
from ..sources.replay import ReplaySource
from ..settings import CLASSES, shared_dir
from ..stream import StreamEncoder, encode_chunks
from .skin import skin

WINDOWS_MS = (16, 32, 64, 128, 256, 512)
HOP_MAX_TAXELS = 1024  #: largest ``--taxels`` count the hop, served-latency and demand parts run (time)
#: per-class window sets (ms) of the latency and sweep parts, besides the parameter file's own
CLASS_WINDOWS_MS: tuple[dict[str, float], ...] = (
    {"SA1": 16.0, "RA": 16.0, "PC": 128.0},
    {"SA1": 32.0, "RA": 32.0, "PC": 128.0},
    {"SA1": 64.0, "RA": 32.0, "PC": 128.0},
)


def taxel_counts(text: str) -> list[int]:
    """``--taxels``: comma-separated taxel counts, each 1..4096."""
    try:
        counts = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}") from None
    if not counts or not all(1 <= n <= 4096 for n in counts):
        raise argparse.ArgumentTypeError(f"taxel counts must be in 1..4096, got {text!r}")
    return counts


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--taxels", type=taxel_counts, default="1,16,256", help="taxel counts for the timing part")
    p.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per timing run")
    p.add_argument("--params", type=Path, default=None, help="parameter file (default: shipped)")
    p.add_argument("--trials", type=int, default=40, help="trials per protocol for the window sweep")
    p.add_argument("--soak-hours", type=float, default=0.0, help="also soak with this many simulated hours")
    p.add_argument("--latency-seconds", type=float, default=30.0, help="simulated seconds per latency run (1 ms chunks)")
    p.add_argument("--skip-sweep", action="store_true", help="only the timing and latency parts")
    p.add_argument("--skin", action="store_true", help="only the large-skin part: activity-driven against dense "
                   "compute, 4096 to 65,536 taxels (bench/skin.py)")
    p.add_argument("--skin-seconds", type=float, default=3.0, help="measured seconds of signal per large-skin run")


def _scene_chunks(n_taxels: int, seconds: float, update_s: float, seed: int = 0) -> list[RawChunk]:
    from ..raw import taxel_grid
    from ..simulator.scene import SceneSource

    src = SceneSource(taxels_xy_mm=taxel_grid(n_taxels), seed=seed)
    return [src.read(update_s) for _ in range(int(round(seconds / update_s)))]


def _time_updates(
    params: EncoderParams, chunks: list[RawChunk], n_taxels: int, dtype: type, active: dict[str, list[int]] | None = None,
    taxel_block: int | None = None,
) -> tuple[np.ndarray, float]:
    """Wall time of every update after warm-up (s) and the process CPU time per update (s, all threads)."""
    se = StreamEncoder(params, n_taxels, dtype=dtype, taxel_block=taxel_block)
    if active is not None:
        se.set_active(active)
    warm = warmup_updates(se, params)
    for c in chunks[:warm]:  # until the first output: JIT dispatch and caches outside the measurement
        se.process(c)
    times = np.empty(len(chunks) - warm)
    cpu = time.process_time()
    for i, c in enumerate(chunks[warm:]):
        t = time.perf_counter()
        se.process(c)
        times[i] = time.perf_counter() - t
    return times, (time.process_time() - cpu) / max(times.size, 1)


def warmup_updates(se: StreamEncoder, params: EncoderParams) -> int:
    """Updates before the chain first emits output (latency) plus two."""
    return int(np.ceil(max(se.latency_s.values()) / (params.preprocess.update_ms / 1000.0))) + 2


def timing(params: EncoderParams, taxels: list[int], seconds: float) -> None:
    """Compute per update with the default threads (float64 and float32 preprocessing) and, where
    they are more than one, float64 on one thread: wall time per update, process CPU time per update
    (all threads), and the speed-up of the threads (one thread's wall mean / theirs)."""
    update_s = params.preprocess.update_ms / 1000.0
    threads = parallel.thread_count()
    print(f"== compute time per {params.preprocess.update_ms:g} ms update ({windows_label(params)}, 3 classes, one taxel block; "
          f"wall time, and process CPU time over all threads; {threads} threads by default, TOUCHREAL_THREADS)")
    print(f"{'taxels':>6} {'dtype':>7} {'threads':>7} {'mean ms':>8} {'p95 ms':>8} {'p99 ms':>8} {'max ms':>8} {'cpu ms':>7} "
          f"{'real-time x':>11} {'speed-up':>8}")
    for n in taxels:
        chunks = _scene_chunks(n, seconds, update_s)
        runs = [(np.float64, threads), (np.float32, threads)] + ([(np.float64, 1)] if threads > 1 else [])
        means = {}
        for dtype, k in runs:
            parallel.set_thread_count(k)
            try:
                times, cpu = _time_updates(params, chunks, n, dtype)
            finally:
                parallel.set_thread_count(None)
            ms = times * 1000
            means[(np.dtype(dtype).name, k)] = ms.mean()
            gain = means.get(("float64", 1), np.nan) / means[("float64", threads)] if k == 1 else np.nan
            print(
                f"{n:6d} {np.dtype(dtype).name:>7} {k:7d} {ms.mean():8.3f} {np.percentile(ms, 95):8.3f} "
                f"{np.percentile(ms, 99):8.3f} {ms.max():8.3f} {cpu * 1000:7.3f} {update_s * 1000 / ms.mean():11.2f} "
                + (f"{gain:8.2f}" if k == 1 else f"{'':>8}")
            )


def hop_cost(params: EncoderParams, taxels: list[int], seconds: float, hops_ms: tuple[float, ...] = (5.0, 10.0)) -> None:
    """Compute per second of sensor time on the service's hop against the ``update_ms`` update, in
    the service's taxel blocks of 64 and (above 64 taxels) in one block (``--taxel-block 0``)."""
    update_s = params.preprocess.update_ms / 1000.0
    print(f"\n== compute per second of sensor time: hop against the {params.preprocess.update_ms:g} ms update "
          f"({windows_label(params)}; process CPU time, all threads, best of 3)")
    print(f"{'taxels':>6} {'block':>5} {'chunks':>14} {'ms per s':>9} {'x update':>9} {'us per call':>11}")
    for n in taxels:
        runs = {None: _scene_chunks(n, seconds, update_s)} | {h: _scene_chunks(n, seconds, h / 1000.0) for h in hops_ms}
        for block in ([64, None] if n > 64 else [None]):
            best: dict[float | None, float] = {}
            for _ in range(3):  # interleaved, so a shared machine's load hits every variant alike
                for h, chunks in runs.items():
                    step = update_s if h is None else h / 1000.0
                    se = StreamEncoder(params, n, taxel_block=block, update_s=None if h is None else update_s)
                    se.set_active({c: range(n) for c in se.classes})  # spikes of every column, no channels
                    warm = min(int(np.ceil(0.3 / step)), len(chunks) // 2)  # past the stream start (hum estimate, first frames)
                    for c in chunks[:warm]:
                        se.process(c)
                    t = time.process_time()  # CPU time of the process (every thread): a shared machine's load does not count
                    for c in chunks[warm:]:
                        se.process(c)
                    per_s = (time.process_time() - t) / ((len(chunks) - warm) * step)
                    best[h] = min(best.get(h, np.inf), per_s)
            for h, per_s in best.items():
                step = update_s if h is None else h / 1000.0
                label = f"{params.preprocess.update_ms:g} ms update" if h is None else f"{h:g} ms hop"
                print(f"{n:6d} {block or n:5d} {label:>14} {per_s * 1000:9.2f} {per_s / best[None]:9.2f} {per_s * step * 1e6:11.1f}")


def served_latency(params: EncoderParams, taxels: list[int], seconds: float, hop_ms: float = 5.0) -> None:
    """Per class: emission (the hop's newest sample + compute) minus the causing sample, as the service
    chunks the sim."""
    from ..sources.live import SimLiveSource

    update_s = params.preprocess.update_ms / 1000.0
    delay = np.array([params.classes[c].delay_ms / 1000.0 if c in params.classes else 0.0 for c in CLASSES])
    print(f"\n== emission minus the causing sample (ms), the sim chunked as served ({windows_label(params)}), "
          f"{seconds:g} s; p50 / p95 / max")
    print(f"{'taxels':>6} {'chunks':>14} {'compute/call':>12} " + " ".join(f"{c:>20}" for c in CLASSES))
    for n in taxels:
        for hop_s in (update_s, hop_ms / 1000.0):
            src = SimLiveSource(n, hop_s, seed=0)
            se = StreamEncoder(params, n, taxel_block=64 if n > 64 else None, update_s=update_s)
            se.set_active({c: range(n) for c in se.classes})
            lat: list[list[np.ndarray]] = [[] for _ in CLASSES]
            spent, calls = 0.0, 0
            while src.scene.time_s < seconds:
                end = src.next_newest_s()
                chunk = src.read_hop()
                t = time.perf_counter()
                ev = se.process(chunk)
                dt = time.perf_counter() - t
                if end < 0.5:  # stream start (hum estimate, JIT dispatch)
                    continue
                spent, calls = spent + dt, calls + 1
                for i in range(len(CLASSES)):
                    sel = ev.cls == i
                    lat[i].append(end + dt - (ev.t_s[sel] - delay[i]))
            label = f"{hop_s * 1000:g} ms " + ("update" if hop_s == update_s else "hop")
            cols = []
            for parts in lat:
                ms = np.concatenate(parts) * 1000 if parts else np.zeros(0)
                cols.append(f"{np.median(ms):6.1f} {np.percentile(ms, 95):6.1f} {ms.max():6.1f}" if ms.size else f"{'-':>20}")
            print(f"{n:6d} {label:>14} {spent / max(calls, 1) * 1000:9.3f} ms " + " ".join(f"{c:>20}" for c in cols))


def with_class_windows(params: EncoderParams, windows: dict[str, float | None]) -> EncoderParams:
    """``params`` with the given classes on their own causal windows (ms)."""
    classes = {c: cp.model_copy(update={"window_ms": windows.get(c, cp.window_ms)}) for c, cp in params.classes.items()}
    return params.model_copy(update={"classes": classes, "version": 3})


def windows_label(params: EncoderParams) -> str:
    """``SA1 16 / RA 16 / PC 128`` (ms; ``ST`` for a class that reads no PVDF channel)."""
    from ..stream import class_source

    return " / ".join(f"{c} {'ST' if class_source(params, c) is None else format(params.window_ms(c), 'g')}" for c in params.classes)


def measure_latency(params: EncoderParams, seconds: float, chunk_s: float = 0.001, skip_s: float = 0.5) -> tuple[dict[str, np.ndarray], float]:
    """Emission minus stamp (s) of every spike per class, raw (``delay_ms`` included), for the live
    scene fed in ``chunk_s`` chunks (spikes emitted in the first ``skip_s`` are left out: stream
    start), and the mean compute time per chunk (s)."""
    from ..simulator.scene import SceneSource

    se = StreamEncoder(params, 1)
    src = SceneSource(seed=0)
    lat: dict[str, list[np.ndarray]] = {c: [] for c in se.classes}
    spent = 0.0
    n = int(round(seconds / chunk_s))
    for _ in range(n):
        chunk = src.read(chunk_s)
        t = time.perf_counter()
        ev = se.process(chunk)
        spent += time.perf_counter() - t
        now = max(float(x[-1]) for x in (chunk.st_t, chunk.pvdf_t) if x.size)
        if now >= skip_s:
            for c in se.classes:
                lat[c].append(now - ev.train(c))
    return {c: np.concatenate(v) if v else np.zeros(0) for c, v in lat.items()}, spent / n


def latency(params: EncoderParams, seconds: float) -> None:
    print(f"\n== latency per class: emission - stamp (ms) on the sensor clock, live scene in 1 ms chunks, {seconds:g} s")
    print(f"{'windows (ms)':<28} {'class':>5} {'bound':>6} {'mean':>7} {'p95':>7} {'max':>7} {'raw mean':>8} {'raw max':>8} {'delay':>7} {'spikes':>6} {'us/chunk':>8}")
    for p in [params] + [with_class_windows(params, w) for w in CLASS_WINDOWS_MS]:
        se = StreamEncoder(p, 1)
        lat, per_chunk = measure_latency(p, seconds)
        for c in se.classes:
            raw = lat[c] * 1000
            own = raw + p.classes[c].delay_ms  # delay_ms treated as 0: the pipeline's own latency
            stats = (f"{own.mean():7.2f} {np.percentile(own, 95):7.2f} {own.max():7.2f} {raw.mean():8.2f} {raw.max():8.2f}"
                     if raw.size else f"{'-':>7} {'-':>7} {'-':>7} {'-':>8} {'-':>8}")
            print(f"{windows_label(p):<28} {c:>5} {1000 * se.latency_s[c]:6.1f} {stats} {p.classes[c].delay_ms:7.1f} {raw.size:6d} {per_chunk * 1e6:8.1f}")


def demand(params: EncoderParams, n_taxels: int, seconds: float) -> None:
    """Compute time per update of one stream of ``n_taxels`` for several subscription sets."""
    update_s = params.preprocess.update_ms / 1000.0
    chunks = _scene_chunks(n_taxels, seconds, update_s)
    few = min(16, n_taxels)
    cases = {
        "every column": None,
        f"{few} taxels, all classes": {c: list(range(few)) for c in params.classes},
        "1 taxel, all classes": {c: [0] for c in params.classes},
        "1 taxel, first class": {next(iter(params.classes)): [0]},
        "nobody (acquisition only)": {},
    }
    print(f"\n== demand: compute time per {params.preprocess.update_ms:g} ms update, {n_taxels} taxels ({windows_label(params)})")
    print(f"{'active columns':<28} {'taxel block':>11} {'mean ms':>8} {'p95 ms':>8}")
    for name, active in cases.items():
        for block in (None, 16):
            ms = _time_updates(params, chunks, n_taxels, np.float64, active, block)[0] * 1000
            print(f"{name:<28} {block or n_taxels:>11} {ms.mean():8.3f} {np.percentile(ms, 95):8.3f}")


def _sweep_dataset(n_trials: int) -> tuple[Dataset, str]:
    rig = shared_dir() / "datasets" / "rig-v1"
    if (rig / "manifest.json").is_file():
        return Dataset.open(rig), f"rig-v1 ({rig})"
    from ..simulator.simulate import simulate_dataset

    out = Path(tempfile.mkdtemp(prefix="touchreal-bench-"))
    for proto in ("ramp", "sine"):
        simulate_dataset(proto, out / proto, trials=n_trials, seed=0)
    return Dataset.open(out / "ramp"), f"simulated ({out})"


def _pick(ds: Dataset, protocol: str, n: int) -> list[dict]:
    entries = ds.entries(protocol)
    if not entries:
        return []
    step = max(1, len(entries) // n)
    return entries[::step][:n]


def sweep(params: EncoderParams, n_trials: int) -> None:
    ds, name = _sweep_dataset(n_trials)
    trials = []
    datasets = [ds]
    sine_root = ds.root.parent / "sine"
    if not ds.entries("sine") and (sine_root / "manifest.json").is_file():
        datasets.append(Dataset.open(sine_root))
    for d in datasets:
        for proto in ("ramp", "sine"):
            trials += [d.load(e) for e in _pick(d, proto, n_trials)]
    print(f"\n== run time against error per causal window ({len(trials)} ramp+sine trials of {name}; "
          "reference: 128 ms, float64; VR tau 10 ms)")

    def encode_all(p: EncoderParams, dtype: type) -> tuple[list[dict[str, np.ndarray]], float]:
        out, spent, updates = [], 0.0, 0
        for tr in trials:
            chunks = list(ReplaySource(tr).chunks(p.preprocess.update_ms / 1000.0))
            t = time.perf_counter()
            ev = encode_chunks(p, chunks, dtype=dtype)
            spent += time.perf_counter() - t
            updates += len(chunks)
            out.append({c: ev.train(c) for c in CLASSES})
        return out, spent / updates * 1000

    def one_window(w: float) -> EncoderParams:
        pre = params.preprocess.model_copy(update={"window_ms": w})
        return with_class_windows(params.model_copy(update={"preprocess": pre}), {c: None for c in params.classes})

    ref, _ = encode_all(one_window(128.0), np.float64)
    rows = [(f"all {w}", one_window(float(w)), dtype) for w in WINDOWS_MS for dtype in ((np.float64, np.float32) if w == 128 else (np.float64,))]
    rows += [(windows_label(p), p, np.float64) for p in [params] + [with_class_windows(params, w) for w in CLASS_WINDOWS_MS]]
    rows += [(windows_label(params), params, np.float32)]  # the served windows in float32
    print(f"{'windows (ms)':>28} {'dtype':>7} {'ms/update':>9} " + " ".join(f"{c + ' cnt%':>9} {c + ' VR':>7}" for c in CLASSES))
    served: dict[str, list[dict[str, np.ndarray]]] = {}
    for label, p, dtype in rows:
        got, ms = encode_all(p, dtype)
        if p is params:
            served[np.dtype(dtype).name] = got
        print(f"{label:>28} {np.dtype(dtype).name:>7} {ms:9.3f} " + _errors(got, ref))
    print(f"{'float32 against float64':>28} {'':>7} {'':>9} " + _errors(served["float32"], served["float64"]) + "  (served windows)")


def _errors(got: list[dict[str, np.ndarray]], ref: list[dict[str, np.ndarray]]) -> str:
    """Per class: |count difference| in % of the reference's spikes and mean VR distance (tau 10 ms)."""
    cols = []
    for c in CLASSES:
        n_ref = np.array([len(r[c]) for r in ref], float)
        n_got = np.array([len(g[c]) for g in got], float)
        cnt = 100 * np.abs(n_got - n_ref).sum() / max(n_ref.sum(), 1.0)
        vr = np.mean([vr_distance(g[c], r[c], 0.01) for g, r in zip(got, ref)])
        cols.append(f"{cnt:9.2f} {vr:7.3f}")
    return " ".join(cols)


def soak(params: EncoderParams, hours: float) -> None:
    from ..simulator.scene import SceneSource

    se = StreamEncoder(params, 1)
    src = SceneSource(seed=1)
    chunk_s, total = 1.0, int(hours * 3600)
    t0 = time.perf_counter()
    first_bytes, peak, spikes = None, 0.0, 0
    for i in range(total):
        spikes += len(se.process(src.read(chunk_s)))
        if i % 60 == 0 or i == total - 1:
            finite, mag, nbytes = se.state_report()
            if not finite:
                raise RuntimeError(f"non-finite state after {i} s")
            peak = max(peak, mag)
            first_bytes = nbytes if first_bytes is None else first_bytes
    wall = time.perf_counter() - t0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\n== soak: {hours:g} h simulated in {wall:.0f} s ({hours * 3600 / wall:.0f}x real time), {spikes} spikes")
    print(f"state finite throughout; largest |state| {peak:.3g}; state bytes start {first_bytes} end {nbytes}; max RSS {rss_mb:.0f} MB")


def run(args: argparse.Namespace) -> int:
    params = EncoderParams.load(args.params) if args.params else default_params()
    if args.skin:
        skin(params, args.skin_seconds)
        return 0
    timing(params, args.taxels, args.seconds)
    hop_taxels = sorted({1} | {n for n in args.taxels if n <= HOP_MAX_TAXELS})  # the hop parts run in blocks of 64
    hop_cost(params, hop_taxels, min(args.seconds, 10.0))
    served_latency(params, [1, max(hop_taxels)], min(args.seconds, 10.0))
    demand(params, max(hop_taxels), args.seconds)
    latency(params, args.latency_seconds)
    if not args.skip_sweep:
        sweep(params, args.trials)
    if args.soak_hours > 0:
        soak(params, args.soak_hours)
    return 0
