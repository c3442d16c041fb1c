"""Spikes at the turning points of the ramp command (paper section 2.5.2: PC-like responses are
expected "near high-acceleration turning points").

A ramp command (indent at ``v_up``, hold, release at ``v_down``) has four turning points, where
its velocity jumps: ``onset`` (0 -> v_up), ``hold`` start (v_up -> 0), ``release`` start
(0 -> -v_down) and release ``end`` (-v_down -> 0). Without a hold the middle two are one ``peak``
(v_up -> -v_down). Every spike of a trial is assigned to the nearest turning point: window edges
lie at the midpoints between consecutive turning points; the first and last windows are open.

Per class, turning point and speed (``v_up`` for onset, hold and peak; ``v_down`` for release and
end), over the trials:

* ``ts_spikes``: mean TouchSim spikes per train in the window; ``tr_spikes``: mean TouchReal spikes
  per trial;
* ``count_error``: mean over trials of |N_TR - N_TS| (spikes; N_TS = the trial's mean over its
  TouchSim trains);
* ``offset_ms``: TouchReal's first spike in the window minus the median first TouchSim spike in it
  (median and quartiles over the trials where both fired), and ``ts_latency_ms`` / ``tr_latency_ms``:
  the first spikes' median latency from the commanded turning point.

Times are relative to the commanded onset, as in :class:`~touchreal.analysis.trials.EvalTrial`.
Pure computation: no I/O.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

EVENTS = ("onset", "hold", "peak", "release", "end")


def is_commanded_ramp(entry: dict[str, Any]) -> bool:
    """A ramp trial that describes its commanded ramp (speeds and turning-point times); a recorded
    live session (clients/examples/record_session.py) is filed as ``ramp`` without them."""
    p, ev = entry.get("params"), entry.get("events")
    return (entry.get("protocol") == "ramp" and isinstance(p, dict) and isinstance(ev, dict)
            and {"v_up_mm_s", "v_down_mm_s"} <= p.keys() and {"hold_start_s", "release_start_s"} <= ev.keys())


def turning_points(entry: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(name, time in s after the commanded onset, speed in mm/s) of a ramp entry's turning points."""
    p, ev, on = entry["params"], entry["events"], float(entry["onset_s"])
    up, down = float(p["v_up_mm_s"]), float(p["v_down_mm_s"])
    hold, release, end = ev["hold_start_s"] - on, ev["release_start_s"] - on, float(entry["stim_end_s"]) - on
    if release - hold > 1e-9:
        return [("onset", 0.0, up), ("hold", hold, up), ("release", release, down), ("end", end, down)]
    return [("onset", 0.0, up), ("peak", hold, up), ("end", end, down)]


def window_edges(times: Sequence[float]) -> np.ndarray:
    """Inner edges (s) of the nearest-turning-point windows: the midpoints between consecutive
    turning points (``len(times) - 1`` values; a spike on an edge belongs to the later window)."""
    t = np.asarray(times, np.float64)
    return 0.5 * (t[1:] + t[:-1])


def split_at_turning_points(spikes: np.ndarray, times: Sequence[float]) -> list[np.ndarray]:
    """Sorted spike times (s) -> one array per turning point (nearest-turning-point windows)."""
    edges = np.concatenate(([-np.inf], window_edges(times), [np.inf]))
    idx = np.searchsorted(np.asarray(spikes, np.float64), edges)
    return [spikes[idx[i] : idx[i + 1]] for i in range(edges.size - 1)]


def shift_windows(spikes: np.ndarray, times: Sequence[float], shifts_s: Sequence[float]) -> np.ndarray:
    """Sorted spike times (s) with the spikes of each nearest-turning-point window moved by that
    window's shift (s)."""
    parts = split_at_turning_points(np.sort(np.asarray(spikes, np.float64)), times)
    return np.sort(np.concatenate([p + float(d) for p, d in zip(parts, shifts_s)] or [np.zeros(0)]))


def fill_missing_spikes(
    spikes: np.ndarray, ts_trains: Sequence[np.ndarray], times: Sequence[float], jitter_s: float = 0.0, rng: np.random.Generator | None = None
) -> np.ndarray:
    """A TouchReal train (s) with the spikes it misses at the turning points added (the oracle of the
    report's missing-spike bound).

    In every nearest-turning-point window where the train has ``m`` spikes and TouchSim's trains have
    ``n = round(mean count) > m``, spikes number ``k = m .. n-1`` are added, each at the median over
    the TouchSim trains that have a k-th spike in the window of that spike's time, plus Gaussian
    jitter of standard deviation ``jitter_s`` (s). Spikes already there are kept unchanged; windows
    with ``m >= n`` are left alone. Returns a new sorted array."""
    mine = split_at_turning_points(np.sort(np.asarray(spikes, np.float64)), times)
    refs = [split_at_turning_points(np.sort(np.asarray(s, np.float64)), times) for s in ts_trains]
    add: list[float] = []
    for i, part in enumerate(mine):
        want = int(np.round(np.mean([r[i].size for r in refs]))) if refs else 0
        for k in range(part.size, want):
            add.append(float(np.median([r[i][k] for r in refs if r[i].size > k])))
    extra = np.asarray(add, np.float64)
    if jitter_s > 0 and extra.size:
        extra = extra + (rng if rng is not None else np.random.default_rng()).normal(0.0, jitter_s, extra.size)
    return np.sort(np.concatenate((np.asarray(spikes, np.float64), extra)))


def _quartiles(v: list[float]) -> list[float] | None:
    return np.percentile(v, [25, 50, 75]).tolist() if v else None


def turning_point_table(trials: Sequence[Any], classes: Sequence[str]) -> dict[str, list[dict[str, Any]]]:
    """Per class: one row per (turning point, speed) over the ramp trials (objects with ``entry``,
    ``tr`` and ``ts`` as :class:`~touchreal.analysis.trials.EvalTrial`), ordered by turning point
    and speed."""
    out: dict[str, list[dict[str, Any]]] = {}
    for cls in classes:
        acc: dict[tuple[str, float], dict[str, list[float]]] = {}
        for tr in trials:
            if not is_commanded_ramp(tr.entry) or not tr.ts.get(cls):
                continue
            tps = turning_points(tr.entry)
            times = [t for _, t, _ in tps]
            mine = split_at_turning_points(np.sort(tr.tr[cls]), times)
            refs = [split_at_turning_points(np.sort(s), times) for s in tr.ts[cls]]
            for i, (name, t_ev, speed) in enumerate(tps):
                a = acc.setdefault((name, speed), {k: [] for k in ("ts", "tr", "err", "offset", "ts_lat", "tr_lat")})
                n_ts = float(np.mean([r[i].size for r in refs]))
                a["ts"].append(n_ts)
                a["tr"].append(float(mine[i].size))
                a["err"].append(abs(mine[i].size - n_ts))
                firsts = [r[i][0] for r in refs if r[i].size]
                if firsts:
                    a["ts_lat"].append(1e3 * (float(np.median(firsts)) - t_ev))
                if mine[i].size:
                    a["tr_lat"].append(1e3 * (float(mine[i][0]) - t_ev))
                    if firsts:
                        a["offset"].append(1e3 * (float(mine[i][0]) - float(np.median(firsts))))
        rows = []
        for (name, speed), a in sorted(acc.items(), key=lambda kv: (EVENTS.index(kv[0][0]), kv[0][1])):
            rows.append(
                {
                    "event": name,
                    "speed_mm_s": speed,
                    "n_trials": len(a["ts"]),
                    "ts_spikes": float(np.mean(a["ts"])),
                    "tr_spikes": float(np.mean(a["tr"])),
                    "count_error": float(np.mean(a["err"])),
                    "offset_ms_quartiles": _quartiles(a["offset"]),
                    "n_offsets": len(a["offset"]),
                    "ts_latency_ms": float(np.median(a["ts_lat"])) if a["ts_lat"] else None,
                    "tr_latency_ms": float(np.median(a["tr_lat"])) if a["tr_lat"] else None,
                }
            )
        out[cls] = rows
    return out
