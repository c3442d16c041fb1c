"""``touchreal demo``: the end-to-end pipeline on the simulated e-skin, no hardware, no shared data.

Runs the live scene (press-hold-release, vibration bursts, texture slides) through the online chain
in 32 ms updates, faster than real time, prints a per-class spike summary with the measured compute
time per update, and writes a figure (force, PVDF, SA1/RA/PC rasters) and the spike times.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ..params import EncoderParams, default_params
from ..preprocess.pipeline import Channels
from ..settings import CLASSES


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="encode a simulated e-skin session and plot the spikes")
    p.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    p.add_argument("--seconds", type=float, default=8.0, help="simulated session length (s)")
    p.add_argument("--taxels", type=int, default=1, help="number of taxels")
    p.add_argument("--params", type=Path, default=None, help="parameter file (default: shipped)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..raw import taxel_grid
    from ..simulator.scene import SceneSource
    from ..bench.encoder import warmup_updates
    from ..encoding.encoder import SpikeEvents
    from ..stream import StreamEncoder

    params = EncoderParams.load(args.params) if args.params else default_params()
    update_s = params.preprocess.update_ms / 1000.0
    source = SceneSource(taxels_xy_mm=taxel_grid(args.taxels), seed=args.seed)
    se = StreamEncoder(params, args.taxels)
    blocks, events, compute = [], [], []
    for _ in range(int(round(args.seconds / update_s))):
        chunk = source.read(update_s)
        t = time.perf_counter()
        ch, ev = se.process_channels(chunk)
        compute.append(time.perf_counter() - t)
        blocks.append(ch)
        events.append(ev)
    channels = Channels.concatenate(blocks, args.taxels)
    spikes = SpikeEvents.concatenate(events)

    args.out.mkdir(parents=True, exist_ok=True)
    duration = channels.n_samples / channels.fs_hz
    print(f"TouchReal demo: {args.seconds:g} s simulated e-skin, {args.taxels} taxel(s), "
          f"window {params.preprocess.window_ms:g} ms, update {params.preprocess.update_ms:g} ms")
    steady = compute[warmup_updates(se, params) :]
    print(f"compute per update (after warm-up): mean {1000 * np.mean(steady):.3f} ms, max {1000 * np.max(steady):.3f} ms; "
          "algorithmic latency " + ", ".join(f"{c} {1000 * v:.1f} ms" for c, v in se.latency_s.items()))
    trains = {}
    for c in CLASSES:
        tr = spikes.train(c, 0)
        trains[c] = tr.tolist()
        print(f"  {c:>3}: {tr.size:5d} spikes, mean rate {tr.size / max(duration, 1e-9):6.1f} Hz (taxel 0)")
    (args.out / "spikes.json").write_text(json.dumps(trains))
    png = args.out / "raster.png"
    _plot(channels, spikes, png)
    print(f"wrote {png} and {args.out / 'spikes.json'}")
    return 0


def _plot(channels: Channels, spikes, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = channels.t_s
    fig, axes = plt.subplots(5, 1, figsize=(11, 7), sharex=True, gridspec_kw={"height_ratios": [2, 2, 1, 1, 1]})
    axes[0].plot(t, channels.data[:, 0, 0], color="k", lw=0.8)
    axes[0].set_ylabel("ST (N)")
    axes[1].plot(t, channels.data[:, 0, 2], color="0.3", lw=0.5)
    axes[1].set_ylabel("PVDF (V)")
    colours = {"SA1": "#329f28", "RA": "#1e78b4", "PC": "#ff7f00"}
    for ax, c in zip(axes[2:], CLASSES):
        tr = spikes.train(c, 0)
        ax.vlines(tr, 0, 1, color=colours[c], lw=0.6)
        ax.set_ylabel(c, rotation=0, labelpad=15)
        ax.set_yticks([])
    axes[-1].set_xlabel("time (s, recording clock)")
    fig.suptitle("TouchReal on the simulated e-skin: preprocessed channels and afferent spikes")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
