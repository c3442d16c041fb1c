"""Decoders: onnxruntime time per update for 1 and 256 taxels, and run time against accuracy per window.

Per model, one update = one ``session.run`` on a batch of (taxels, n_bins, n_classes) Poisson
counts (what :class:`~touchreal.decoding.streaming.StreamingDecoder` sends every step, a stateful model's
state fed back), one intra-op thread; ``push`` adds the decoder's binning of one update's spike events (about 40
spikes/s per taxel and class) to that. Accuracy columns are the held-out metrics recorded in each
model's metadata by ``touchreal decoders train`` (R^2 for force, accuracy for texture). A model that
reads the scanning speed gets one speed row for the batch (:data:`BENCH_SPEED_MM_S`), as a robot
that slides the whole patch supplies it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

BENCH_SPEED_MM_S = 40.0  #: the scanning speed fed to models that read it (mm/s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", help="models folder with sweep/ (default: the installed models)")
    parser.add_argument("--updates", type=int, default=400, help="timed updates per case (default 400)")
    parser.add_argument("--taxels", type=int, nargs="+", default=[1, 256], help="taxel counts (default 1 256)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads (default 1)")


def _times_ms(fn, n: int) -> tuple[float, float, float, float]:
    """(wall mean, wall p99, wall median, CPU mean = process user + sys) of ``n`` timed calls after a
    warm-up (ms); the CPU time does not grow with other jobs' load as the wall time does."""
    for _ in range(min(20, n)):
        fn()
    t = np.empty(n)
    c0 = time.process_time()
    for i in range(n):
        t0 = time.perf_counter()
        fn()
        t[i] = time.perf_counter() - t0
    cpu = (time.process_time() - c0) / n
    return float(t.mean() * 1e3), float(np.percentile(t, 99) * 1e3), float(np.median(t) * 1e3), cpu * 1e3


def _ort_ms(model, n_taxels: int, updates: int, threads: int, rng) -> tuple[float, float, float, float]:
    """One inference per update (a stateful model's state fed back, as the streaming decoder does)."""
    sess = model.session(threads)
    shape = [n_taxels] + model.meta["input"]["shape"][1:]
    x = rng.poisson(0.4, shape).astype(np.float32)
    state = {"s": model.initial_state(n_taxels) if model.stateful else None}
    speed = np.full((1, 1), BENCH_SPEED_MM_S, np.float32) if model.needs_speed else None

    def one() -> None:
        state["s"] = model.run(sess, x, state["s"], speed)[1]

    return _times_ms(one, updates)


def _push_ms(model, n_taxels: int, updates: int, threads: int, rng) -> tuple[float, float, float, float]:
    from touchreal.decoding.streaming import StreamingDecoder
    from touchreal_client.features import CLASSES

    dec = StreamingDecoder(model, range(n_taxels), threads, start_us=0)
    step = model.step_us
    per = max(1, int(round(40 * step / 1e6 * n_taxels)))  # spikes per class per update
    state = {"t": 0}

    def one() -> None:
        t0 = state["t"]
        t = np.sort(rng.integers(t0, t0 + step, per * 3)).astype(np.uint64)
        dec.push(t, rng.integers(0, n_taxels, t.size), np.repeat(np.arange(3), per)[rng.permutation(t.size)],
                 {c: t0 + step for c in CLASSES}, BENCH_SPEED_MM_S)
        state["t"] = t0 + step

    return _times_ms(one, updates)


def run(args: argparse.Namespace) -> int:
    from touchreal.decoding.model import ModelStore, load_model

    if args.models is None:
        store = ModelStore()
        models = [store.load(m["name"]) for m in store.list() if "error" not in m]
    else:
        root = Path(args.models)
        models = [load_model(p) for p in sorted(root.glob("*.onnx")) + sorted((root / "sweep").glob("*.onnx"))]
    if not models:
        raise ValueError("no decoder models to benchmark")
    rng = np.random.default_rng(0)
    product = [m for m in models if m.meta["training"].get("folder", "") == ""]
    print("time per update (ms; wall mean, p99, CPU mean), onnxruntime run and the whole StreamingDecoder.push, threads =", args.threads)
    print(f"{'model':<18} {'taxels':>6} {'ort mean':>9} {'ort p99':>8} {'ort cpu':>8} {'push mean':>10} {'push p99':>9} {'push cpu':>9}")
    for m in product:
        for n in args.taxels:
            om, op, _, oc = _ort_ms(m, n, args.updates, args.threads, rng)
            pm, pp, _, pc = _push_ms(m, n, args.updates, args.threads, rng)
            print(f"{m.name:<18} {n:>6d} {om:>9.3f} {op:>8.3f} {oc:>8.3f} {pm:>10.3f} {pp:>9.3f} {pc:>9.3f}")
    print()
    print("run time against accuracy across decoding windows (held-out metrics from the metadata)")
    big = max(args.taxels)
    print(f"median onnxruntime ms per update for 1 and {big} taxels")
    print(f"{'model':<34} {'window ms':>9} {'ort ms (1)':>10} {f'ort ms ({big})':>12} {'metric':>14} {'value':>7}")
    rows = []
    for m in models:
        meta = m.meta
        if meta["params"].get("pvdf_window_ms") is not None:
            continue  # the preprocessing-window sweep is not a decoding-window cost
        if meta["task"] == "force" and meta["classes"] != ["SA1", "RA"]:
            continue
        kind = "stateful" if m.stateful else meta["features"]["set"]
        key, label = ("r2", f"R^2 {kind}") if meta["task"] == "force" else ("acc", f"acc {kind}")
        rows.append((meta["task"], kind, meta["window_ms"], m, label, meta["metrics"].get(key)))
    for task, fs, w, m, label, value in sorted(rows, key=lambda r: r[:3]):
        one = _ort_ms(m, 1, max(50, args.updates // 4), args.threads, rng)[2]
        many = _ort_ms(m, big, max(50, args.updates // 4), args.threads, rng)[2]
        v = f"{value:.3f}" if isinstance(value, float) else "-"
        print(f"{m.name:<34} {w:>9g} {one:>10.3f} {many:>12.3f} {label:>14} {v:>7}")
    return 0
