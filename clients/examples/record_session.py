"""Record a live session into the TouchReal recording format (docs/recording-format.md), so that
``touchreal encode`` or ``touchreal evaluate`` can read it later.

The stream carries the pipeline's 5 kHz channels (``ST`` in N, ``PVDF`` in V, after the service's
causal filtering), not the raw sensor samples. The recorder subscribes to them undecimated and
writes, per taxel, one trial with SingleTact at 100 Hz (every 50th 5 kHz sample) and PVDF at 2 kHz
(linear interpolation of the 5 kHz samples). The live spikes go in as the trial's reference trains
(one repeat, one model), so ``touchreal evaluate`` compares a re-encoding with what was streamed;
expect them to differ a little: ``encode`` filters the already filtered channels once more. A
live session has no commanded stimulus: ``cmd_depth`` is zeros and the protocol is ``ramp``
(the format's enumeration has no "live" protocol).

    python record_session.py --url http://127.0.0.1:8765 --seconds 20 --out session-ds

Needs only ``touchreal-client`` (numpy writes the .npz files).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from touchreal_client import CLASSES, ChannelsFrame, Client, SpikesFrame, Subscription

ST_FS, PVDF_FS, GRID_FS = 100.0, 2000.0, 5000.0


class SessionBuffer:
    """Sans-I/O: channel and spike frames in, one trial dict per taxel out (recording clock in s,
    t = 0 at the first 5 kHz sample received)."""

    def __init__(self) -> None:
        self.t0_us: int | None = None
        self.samples: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}  # taxel -> [(t_us, (n, 4))]
        self.spikes: dict[tuple[int, int], list[np.ndarray]] = {}  # (taxel, class) -> [t_us]

    def push(self, frame: ChannelsFrame | SpikesFrame) -> None:
        if isinstance(frame, ChannelsFrame):
            t = frame.t0_us + frame.period_us * np.arange(frame.data.shape[0], dtype=np.int64)
            if self.t0_us is None and t.size:
                self.t0_us = int(t[0])
            for i, taxel in enumerate(frame.taxels.tolist()):
                self.samples.setdefault(taxel, []).append((t, frame.data[:, i, :]))
        else:
            for k in range(len(CLASSES)):
                for taxel in np.unique(frame.taxel).tolist():
                    sel = (frame.cls == k) & (frame.taxel == taxel)
                    if sel.any():
                        self.spikes.setdefault((taxel, k), []).append(frame.t_us[sel].astype(np.int64))

    def trials(self) -> dict[int, dict[str, np.ndarray]]:
        out = {}
        for taxel, chunks in self.samples.items():
            t_us = np.concatenate([c[0] for c in chunks])
            data = np.concatenate([c[1] for c in chunks])
            t = (t_us - self.t0_us) / 1e6
            if t.size < 2 or np.any(np.diff(t_us) != 200):
                raise ValueError(f"taxel {taxel}: the 5 kHz channels have holes (frames dropped?); record again")
            k = np.round(t * GRID_FS).astype(np.int64)
            st_sel = k % int(GRID_FS / ST_FS) == 0
            pvdf_t = np.arange(np.ceil(t[0] * PVDF_FS), np.floor(t[-1] * PVDF_FS) + 1) / PVDF_FS
            trial = {
                "st_t": t[st_sel], "st": data[st_sel, 0].astype(np.float32),
                "pvdf_t": pvdf_t, "pvdf": np.interp(pvdf_t, t, data[:, 2]).astype(np.float32),
                "cmd_t0": np.float64(t[0]), "cmd_fs": np.float64(ST_FS),
                "cmd_depth": np.zeros(int(st_sel.sum()), np.float32),
            }
            for k_cls, cls in enumerate(CLASSES):
                tr = self.spikes.get((taxel, k_cls), [])
                s = (np.concatenate(tr) - self.t0_us) / 1e6 if tr else np.zeros(0)
                s = s[(s >= t[0]) & (s <= t[-1])]
                trial[f"ref_{cls}_t"] = s.astype(np.float32)
                trial[f"ref_{cls}_off"] = np.array([[0, s.size]], np.int32)
            out[taxel] = trial
        return out


def write_dataset(root: Path, trials: dict[int, dict[str, np.ndarray]], source: str) -> None:
    (root / "trials").mkdir(parents=True, exist_ok=True)
    entries = []
    for taxel, tr in trials.items():
        tid = f"live-taxel{taxel}"
        np.savez(root / "trials" / f"{tid}.npz", **tr)
        entries.append({
            "id": tid, "file": f"trials/{tid}.npz", "protocol": "ramp", "condition": f"live-taxel{taxel}",
            "repeat": 0, "params": {"live": True, "taxel": taxel}, "onset_s": float(tr["st_t"][0]),
            "stim_end_s": float(tr["st_t"][-1]), "duration_s": float(tr["st_t"][-1] - tr["st_t"][0]),
            "n_st": int(tr["st"].size), "n_pvdf": int(tr["pvdf"].size), "n_cmd": int(tr["cmd_depth"].size),
            "reference": {"repeats": 1, "source": "live stream"},
        })
    manifest = {"name": root.name, "format_version": "1.0",
                "description": f"live session recorded from {source} (channels after the service's filtering; "
                               "reference trains = the live spikes)",
                "channels": {"st": "N @ 100 Hz", "pvdf": "V @ 2 kHz"}, "trials": entries}
    (root / "manifest.json").write_text(json.dumps(manifest, indent=1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8765")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=Path("session-ds"))
    ap.add_argument("--taxels", default=None, help="comma list (default all)")
    args = ap.parse_args(argv)
    taxels = [int(t) for t in args.taxels.split(",")] if args.taxels else None
    buf = SessionBuffer()
    sub = Subscription(taxels=taxels, streams=["spikes", "channels"], decimation=1)
    with Client(args.url) as tr:
        tr.wait_ready(60)
        with tr.stream(sub, queue_frames=4096) as s:
            end = time.monotonic() + args.seconds
            for frame in s.frames():
                buf.push(frame)
                if time.monotonic() >= end:
                    break
            if s.stats.missed_frames:
                print(f"warning: {s.stats.missed_frames} frames were dropped by the server", file=sys.stderr)
    try:
        trials = buf.trials()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    write_dataset(args.out, trials, args.url)
    print(f"{len(trials)} trial(s) in {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
