"""``touchreal evaluate``: reproduce the paper's evaluation (section 3) on a dataset's held-out trials.

Writes ``report.md``, ``metrics.json`` and PNG figures into the report folder. Definitions (also
printed into the report):

* **Held-out trials.** If the parameter file was fitted by ``touchreal fit`` on this dataset (same
  manifest name, provenance carries the split seed), the ramp and sine trials the fit did not use
  (:func:`touchreal.fitting.fit.split_repeats`); otherwise every ramp and sine trial. Spatial
  trials are never used by the fit and are all evaluated.
* **Spike trains** are compared on time since the commanded onset of their own trial (TouchSim
  references and TouchReal outputs both), over the whole recording; TouchReal's stamps are first
  put on the reference clock (stamp minus the parameter file's ``alignment.lag_ms``, the rig's lag).
  Each class runs at its own causal PVDF window.
* **Latency** per class (:mod:`.latency`): the chain's algorithmic latency, and the measured median
  emission minus stamp on a few held-out ramp trials replayed in 1 ms chunks.
* **VR distance** (Fig. 8): van Rossum, tau = 1 ms, elephant normalisation. Per class and
  condition: TS-TS = mean over all distinct pairs of TouchSim trains (all repeats x all models of
  the held-out trials of that condition); TS-TR = mean over all (TouchReal held-out trial, TouchSim
  train) pairs; TR-TR = mean over distinct pairs of TouchReal trains of all recordings of the
  condition (training recordings included: TR-TR measures the sensor pipeline's repeatability and
  involves no reference spikes; ramps have only one held-out recording per condition).
  **inter/intra ratio** = mean over conditions of TS-TR / mean over conditions of TS-TS
  (intra = TouchSim-TouchSim alone); the ratio with intra = mean(TS-TS, TR-TR) is reported too.
* **Spike-count error**: per condition ``|N_TR - N_TS| / N_TS`` with N the mean whole-trial count
  of the held-out TouchReal trials and of the TouchSim trains; mean over conditions with
  ``N_TS >= 1`` (the others are counted and listed as excluded).
* **Frequency response** (Fig. 9, Tables 2-3): rate = spikes in [onset, stimulus end) / burst
  duration; TouchSim observations are single trains (trial x repeat x model), TouchReal
  observations are held-out trials; 95 % t-CIs; two-way ANOVA ``rate ~ C(frequency) * C(source)``
  with Type II sums of squares (statsmodels). A balanced variant (TouchSim averaged per trial) is in
  metrics.json.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..encoding.encoder import channel_currents, encode_population
from ..params import EncoderParams
from ..preprocess.pipeline import preprocess_trial
from ..recording import Dataset
from ..settings import CHANNELS, CLASSES, OUT_FS_HZ
from . import spatial as sp
from . import spiketrains as stn
from . import stats
from . import turning_points as tp
from .latency import latency_table

VR_TAU_S = 0.001
SWEEP_WINDOWS_MS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0)
BOUND_JITTERS_MS = (0.0, 1.0, 2.0, 5.0)  #: jitters of the missing-spike bound
#: Classes of the missing-spike bound: PC, whose TouchSim trains hold about one spike per turning
#: point (SA1 and RA fire many, so their count errors come from rates, not from missed events).
BOUND_CLASSES = ("PC",)
AREA_THRESHOLD = 2.0
SWEEP_THRESHOLDS = np.arange(1, 21)
TARGETS = {
    "vr_ratio_max": {"SA1": 1.2, "RA": 1.3, "PC": 1.5},
    "count_error_max": 0.15,
    "anova_source_p_min": 0.05,
}
FIG7_PREFERRED = "ramp_d1.0_vu40_vd95_h1.8"


@dataclass
class EvalConfig:
    vr_tau_s: float = VR_TAU_S
    sweep_windows_ms: tuple[float, ...] = SWEEP_WINDOWS_MS
    bound_jitters_ms: tuple[float, ...] = BOUND_JITTERS_MS  #: () skips the missing-spike bound
    sweep_max_ramp_conditions: int | None = 64  #: ramp conditions in the window sweep (None = all)
    ramp_condition: str | None = None  #: Fig. 7 condition (default: FIG7_PREFERRED or the first)
    split: str = "auto"  #: auto | all (every trial) | train (the fit's training half)
    latency_trials: int = 1  #: held-out ramp trials replayed to measure the latency (0: algorithmic only)
    seed: int = 0  #: subsampling of the window sweep
    with_sweep: bool = True
    with_spatial: bool = True
    progress: bool = False


@dataclass
class EvalTrial:
    entry: dict[str, Any]
    onset: float
    tr: dict[str, np.ndarray]  # class -> TouchReal train (onset-aligned)
    ts: dict[str, list[np.ndarray]] = field(default_factory=dict)  # class -> TouchSim trains (onset-aligned)
    ts_repeats: dict[str, int] = field(default_factory=dict)
    channels: np.ndarray | None = None  # (T, 4) when kept
    k0: int = 0


def _iter(items, progress: bool, desc: str):
    if progress:
        from tqdm import tqdm

        return tqdm(items, desc=desc, unit="trial", dynamic_ncols=True)
    return items


def run_trials(
    ds: Dataset, entries: Sequence[dict[str, Any]], params: EncoderParams, classes: Sequence[str], keep_channels: bool | set[str] = False,
    window_ms: float | None = None, progress: bool = False, desc: str = "encode",
) -> list[EvalTrial]:
    """Preprocess + encode every entry: each class at its own causal PVDF window (``window_ms``
    overrides every class's), one population per window and trial; spike trains on the reference
    clock (:meth:`EncoderParams.reference_times`), relative to the commanded onset.

    ``keep_channels``: keep the 5 kHz channels of every trial (True) or of the trial ids given; they
    are the channels of the preprocessing window (``params.preprocess.window_ms``, or ``window_ms``)."""
    groups: dict[float, list[str]] = {}
    for c in classes:
        groups.setdefault(float(window_ms if window_ms is not None else params.window_ms(c)), []).append(c)
    kept_w = float(window_ms if window_ms is not None else params.preprocess.window_ms)
    out = []
    for e in _iter(entries, progress, desc):
        trial = ds.load(e)
        onset = float(e["onset_s"])
        trains: dict[str, np.ndarray] = {}
        ch_kept = None
        for w in sorted(set(groups) | ({kept_w} if keep_channels else set())):
            ch = preprocess_trial(trial, params.preprocess.model_copy(update={"window_ms": w}))
            x = np.ascontiguousarray(ch.data[:, 0, :])
            if w == kept_w:
                ch_kept = (x, int(ch.k0))
            on_w = groups.get(w, [])
            if on_w:
                for c, t in zip(on_w, encode_population(x, ch.t0_s, [params.classes[c] for c in on_w])):
                    trains[c] = params.reference_times(t) - onset
        et = EvalTrial(e, onset, {c: trains[c] for c in classes})
        for c in classes:
            if c in trial.reference:
                r = trial.reference[c]
                et.ts[c] = [np.sort(np.asarray(t, np.float64)) - onset for t in r.trains()]
                et.ts_repeats[c] = r.repeats
        if ch_kept is not None and (keep_channels is True or (isinstance(keep_channels, set) and e["id"] in keep_channels)):
            et.channels, et.k0 = ch_kept
        out.append(et)
    return out


def _by_condition(trials: Sequence[EvalTrial]) -> dict[str, list[EvalTrial]]:
    out: dict[str, list[EvalTrial]] = {}
    for t in trials:
        out.setdefault(t.entry["condition"], []).append(t)
    return out


# ------------------------------------------------------------------------ mapping (Fig. 8)


def mapping_metrics(
    held: Sequence[EvalTrial], all_trials: Sequence[EvalTrial], classes: Sequence[str], tau_s: float, ts_ts_cache: dict[tuple[str, str], float] | None = None
) -> dict[str, Any]:
    """Per class: per-condition mean VR distances and spike counts, and their summaries.

    ``ts_ts_cache`` ((class, condition) -> mean TS-TS distance) is filled and reused by calls on
    the same held-out trials, whose TouchSim trains do not change."""
    held_c = _by_condition(held)
    all_c = _by_condition(all_trials)
    out: dict[str, Any] = {}
    for cls in classes:
        rows = []
        for cond, trs in sorted(held_c.items()):
            ts = [t for tr in trs for t in tr.ts.get(cls, [])]
            if not ts:
                continue
            tr = [t.tr[cls] for t in trs]
            key = (cls, cond)
            if ts_ts_cache is None or key not in ts_ts_cache:
                d_tsts = stn.pairwise_upper(stn.vr_distance_matrix(ts, tau_s, presorted=True))
                ts_ts = float(d_tsts.mean()) if d_tsts.size else np.nan
                if ts_ts_cache is not None:
                    ts_ts_cache[key] = ts_ts
            else:
                ts_ts = ts_ts_cache[key]
            d_tstr = stn.vr_distances_between(tr, ts, tau_s)
            tr_all = [t.tr[cls] for t in all_c.get(cond, trs)]
            d_trtr = stn.pairwise_upper(stn.vr_distance_matrix(tr_all, tau_s)) if len(tr_all) > 1 else np.zeros(0)
            rows.append(
                {
                    "condition": cond,
                    "protocol": trs[0].entry["protocol"],
                    "ts_ts": ts_ts,
                    "ts_tr": float(d_tstr.mean()),
                    "tr_tr": float(d_trtr.mean()) if d_trtr.size else np.nan,
                    "n_ts": float(np.mean([t.size for t in ts])),
                    "n_tr": float(np.mean([t.size for t in tr])),
                }
            )
        out[cls] = {"rows": rows, **summarize_mapping(rows)}
    return out


def summarize_mapping(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def summary(sel: list[dict[str, Any]]) -> dict[str, Any]:
        if not sel:
            return {}
        a = {k: np.array([r[k] for r in sel], float) for k in ("ts_ts", "ts_tr", "tr_tr", "n_ts", "n_tr")}
        ts_ts = float(np.nanmean(a["ts_ts"]))
        ts_tr = float(np.nanmean(a["ts_tr"]))
        both = np.isfinite(a["ts_ts"]) & np.isfinite(a["tr_tr"])
        intra_mean = float(np.mean(0.5 * (a["ts_ts"][both] + a["tr_tr"][both]))) if both.any() else np.nan
        inter_both = float(np.mean(a["ts_tr"][both])) if both.any() else np.nan
        valid = a["n_ts"] >= 1.0
        rel = np.abs(a["n_tr"] - a["n_ts"]) / np.where(valid, a["n_ts"], 1.0)
        return {
            "n_conditions": len(sel),
            "vr_ts_ts_mean": ts_ts,
            "vr_ts_tr_mean": ts_tr,
            "vr_tr_tr_mean": float(np.nanmean(a["tr_tr"])) if np.isfinite(a["tr_tr"]).any() else np.nan,
            "vr_ts_ts_median": float(np.nanmedian(a["ts_ts"])),
            "vr_ts_tr_median": float(np.nanmedian(a["ts_tr"])),
            "ratio_inter_intra": ts_tr / ts_ts if ts_ts > 0 else np.nan,
            "ratio_inter_intra_median": float(np.nanmedian(a["ts_tr"]) / np.nanmedian(a["ts_ts"])),
            "ratio_inter_intra_with_trtr": inter_both / intra_mean if intra_mean and np.isfinite(intra_mean) else np.nan,
            "count_error_mean": float(rel[valid].mean()) if valid.any() else np.nan,
            "count_error_median": float(np.median(rel[valid])) if valid.any() else np.nan,
            "count_bias": float(a["n_tr"].sum() / a["n_ts"].sum() - 1.0) if a["n_ts"].sum() > 0 else np.nan,
            "count_error_excluded_conditions": int((~valid).sum()),
        }

    out = {"all": summary(rows)}
    for p in sorted({r["protocol"] for r in rows}):
        out[p] = summary([r for r in rows if r["protocol"] == p])
    return {"summary": out}


# --------------------------------------------------------------------- Table 1 (eq. 11)


def missing_spike_bound(
    held: Sequence[EvalTrial], classes: Sequence[str], tau_s: float, jitters_ms: Sequence[float] = BOUND_JITTERS_MS, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """What the held-out VR ratio and count error would be if TouchReal also fired the spikes it
    misses at the ramps' turning points (:func:`~touchreal.analysis.turning_points.fill_missing_spikes`:
    at TouchSim's own median times, plus Gaussian jitter of each sd in ``jitters_ms``); sine trials
    and the spikes already fired are kept. It bounds what adding spikes can do: an encoder can place
    them no closer to TouchSim's than the sensor's own timing of the turning points allows.

    Per class two bases: ``as_fitted`` (TouchReal's spikes as they are) and ``unbiased`` (every
    ramp spike first moved by minus the median offset of its turning point and speed in the
    turning-point table: an oracle no causal encoder has). Each holds ``ratio_inter_intra`` and
    ``count_error`` of the base and ``filled``: one row per jitter with the jitter (ms),
    ``ratio_inter_intra``, ``count_error`` and ``added_per_ramp_trial``."""
    out: dict[str, dict[str, Any]] = {}
    for cls in classes:
        ramps = [t for t in held if tp.is_commanded_ramp(t.entry) and t.ts.get(cls)]
        if not ramps:
            continue
        cache: dict[tuple[str, str], float] = {}

        def replaced(trains: dict[int, np.ndarray]) -> list[EvalTrial]:
            return [EvalTrial(t.entry, t.onset, {cls: trains[id(t)]}, {cls: t.ts[cls]}) if id(t) in trains else t for t in held]

        def summary(trials: list[EvalTrial]) -> dict[str, float]:
            s = mapping_metrics(trials, trials, [cls], tau_s, cache)[cls]["summary"]["all"]
            return {"ratio_inter_intra": float(s["ratio_inter_intra"]), "count_error": float(s["count_error_mean"])}

        points = {id(t): tp.turning_points(t.entry) for t in ramps}
        times = {k: [x for _, x, _ in p] for k, p in points.items()}
        median_offset = {(r["event"], r["speed_mm_s"]): r["offset_ms_quartiles"][1] / 1000.0 if r["offset_ms_quartiles"] else 0.0
                         for r in tp.turning_point_table(ramps, [cls])[cls]}
        bases = {
            "as_fitted": {id(t): t.tr[cls] for t in ramps},
            "unbiased": {id(t): tp.shift_windows(t.tr[cls], times[id(t)], [-median_offset[(n, v)] for n, _, v in points[id(t)]]) for t in ramps},
        }
        res: dict[str, Any] = {}
        for b, (name, base) in enumerate(bases.items()):
            rows = []
            for j, jit in enumerate(jitters_ms):
                rng = np.random.default_rng([seed, b, j])
                filled = {id(t): tp.fill_missing_spikes(base[id(t)], t.ts[cls], times[id(t)], jit / 1000.0, rng) for t in ramps}
                added = sum(filled[k].size - base[k].size for k in filled) / len(ramps)
                rows.append({"jitter_ms": float(jit), **summary(replaced(filled)), "added_per_ramp_trial": added})
            res[name] = {**summary(replaced(base)), "filled": rows}
        out[cls] = res
    return out


def channel_contributions(trials: Sequence[EvalTrial], params: EncoderParams, classes: Sequence[str]) -> dict[str, dict[str, float]]:
    """Eq. (11): share (%) of each channel in the summed |pre-saturation current| per class."""
    out = {}
    for cls in classes:
        tot = np.zeros(4)
        for t in trials:
            if t.channels is not None:
                tot += np.abs(channel_currents(t.channels, params.classes[cls])).sum(axis=0)
        s = tot.sum()
        out[cls] = {ch: float(100.0 * v / s) if s > 0 else 0.0 for ch, v in zip(CHANNELS, tot)}
    return out


# ------------------------------------------------------------- frequency response (Fig. 9)


def frequency_response(sine: Sequence[EvalTrial], classes: Sequence[str]) -> dict[str, Any]:
    freqs = sorted({float(t.entry["params"]["freq_hz"]) for t in sine})
    out: dict[str, Any] = {"freqs_hz": freqs}
    for cls in classes:
        y, fa, src, bal_y, bal_f, bal_s = [], [], [], [], [], []
        curves: dict[str, list[tuple[float, float, float]]] = {"TouchSim": [], "TouchReal": []}
        for f in freqs:
            trs = [t for t in sine if float(t.entry["params"]["freq_hz"]) == f]
            ts_rates, tr_rates = [], []
            for t in trs:
                dur = float(t.entry["stim_end_s"]) - t.onset
                tr_rates.append(stn.firing_rate(t.tr[cls], 0.0, dur))
                per = [stn.firing_rate(x, 0.0, dur) for x in t.ts.get(cls, [])]
                ts_rates += per
                if per:
                    bal_y += [float(np.mean(per)), tr_rates[-1]]
                    bal_f += [f, f]
                    bal_s += ["TouchSim", "TouchReal"]
            curves["TouchSim"].append(stats.mean_ci(ts_rates))
            curves["TouchReal"].append(stats.mean_ci(tr_rates))
            y += ts_rates + tr_rates
            fa += [f] * (len(ts_rates) + len(tr_rates))
            src += ["TouchSim"] * len(ts_rates) + ["TouchReal"] * len(tr_rates)
        res: dict[str, Any] = {
            "curves": {s: {"mean": [c[0] for c in v], "ci_lo": [c[1] for c in v], "ci_hi": [c[2] for c in v]} for s, v in curves.items()},
            "n_obs": {s: int(sum(1 for x in src if x == s)) for s in curves},
        }
        try:
            res["anova"] = stats.two_way_anova(y, fa, src)
            res["anova_balanced"] = stats.two_way_anova(bal_y, bal_f, bal_s)
        except ValueError as exc:
            res["anova_error"] = str(exc)
        tr_mean = np.array(res["curves"]["TouchReal"]["mean"])
        ts_mean = np.array(res["curves"]["TouchSim"]["mean"])
        res["shape"] = {s: _shape(freqs, m) for s, m in (("TouchReal", tr_mean), ("TouchSim", ts_mean))}
        out[cls] = res
    return out


def _shape(freqs: list[float], m: np.ndarray) -> dict[str, Any]:
    from scipy.stats import spearmanr

    if m.size < 3 or not np.all(np.isfinite(m)):
        return {}
    peak = float(freqs[int(np.argmax(m))])
    rho = float(spearmanr(freqs, m).statistic) if np.ptp(m) > 0 else 0.0
    return {
        "peak_hz": peak,
        "band_pass": bool(m.max() > m[0] and m.max() > m[-1]),
        "spearman_rho": rho,
        "rising": bool(rho >= 0.9 and m[-1] > m[0]),
    }


# ------------------------------------------------------------------ spatial (Figs. 10-11)


def spatial_metrics(trials: Sequence[EvalTrial], classes: Sequence[str]) -> dict[str, Any]:
    """SA1/RA from spatial_ramp (levels = depth), PC from spatial_sine (levels = frequency)."""
    out: dict[str, Any] = {}
    plan = {"SA1": ("spatial_ramp", "depth_mm", "depth [mm]"), "RA": ("spatial_ramp", "depth_mm", "depth [mm]"), "PC": ("spatial_sine", "freq_hz", "frequency [Hz]")}
    for cls in classes:
        proto, key, xlabel = plan[cls]
        sel = [t for t in trials if t.entry["protocol"] == proto]
        levels = sorted({float(t.entry["params"][key]) for t in sel})
        res: dict[str, Any] = {"protocol": proto, "xlabel": xlabel, "levels": levels, "conditions": []}
        for lev in levels:
            group = [t for t in sel if float(t.entry["params"][key]) == lev]
            pos: dict[tuple[float, float], dict[str, list[float]]] = {}
            for t in group:
                r, th = float(t.entry["offset_r_mm"]), float(t.entry["offset_theta_deg"])
                if r == 0:
                    th = 0.0
                p = pos.setdefault((r, th), {"tr": [], "ts": []})
                p["tr"].append(t.tr[cls].size)
                if t.ts.get(cls):
                    p["ts"].append(float(np.mean([x.size for x in t.ts[cls]])))
            keys = sorted(pos)
            r = np.array([k[0] for k in keys])
            th = np.array([k[1] for k in keys])
            cond: dict[str, Any] = {"level": lev, "r": r.tolist(), "theta": th.tolist()}
            for s in ("tr", "ts"):
                v = np.array([np.mean(pos[k][s]) if pos[k][s] else np.nan for k in keys])
                cond[f"counts_{s}"] = v.tolist()
                radii, rmean, _ = sp.radial_profile(r, v)
                cond["radii"] = radii.tolist()
                cond[f"radial_{s}"] = rmean.tolist()
                ok = np.isfinite(v)
                if ok.sum() >= 3 and r[ok].max() > 0:
                    m = sp.interpolate_map(r[ok], th[ok], v[ok])
                    cond[f"area_{s}"] = sp.response_area(m, AREA_THRESHOLD)
                    cond[f"area_sweep_{s}"] = sp.area_sweep(m, SWEEP_THRESHOLDS).tolist()
                    if s == "tr":
                        cond["_map_tr"] = m
                else:
                    cond[f"area_{s}"] = np.nan
                    cond[f"area_sweep_{s}"] = [np.nan] * SWEEP_THRESHOLDS.size
                an = sp.anisotropy(r[ok], th[ok], v[ok])
                cond[f"ai2_{s}"] = an.ai2
                cond[f"axis_{s}"] = an.axis_deg
                ang, prof, pstd = sp.angular_profile(r[ok], th[ok], v[ok])
                cond["angles"] = ang.tolist()
                cond[f"profile_{s}"] = prof.tolist()
                cond[f"profile_{s}_std"] = pstd.tolist()
            res["conditions"].append(cond)
        out[cls] = res
    return out


# --------------------------------------------------------------------- window sweep (Fig. 12)


def window_sweep(
    ds: Dataset, entries: Sequence[dict[str, Any]], params: EncoderParams, classes: Sequence[str], cfg: EvalConfig
) -> dict[str, Any]:
    """Mean TS-TR VR distance and spike-count error against the causal PVDF window, with the
    fitted class parameters held fixed (no refit per window; the gate thresholds follow the
    calibrated noise spectrum for each window length)."""
    res: dict[str, Any] = {"windows_ms": list(cfg.sweep_windows_ms), "vr": {c: [] for c in classes}, "count_error": {c: [] for c in classes}, "ts_ts": {}}
    for w in cfg.sweep_windows_ms:
        trials = run_trials(ds, entries, params, classes, window_ms=w, progress=cfg.progress, desc=f"window {w:g} ms")
        m = mapping_metrics(trials, trials, classes, cfg.vr_tau_s)
        for c in classes:
            s = m[c]["summary"]["all"]
            res["vr"][c].append(s["vr_ts_tr_mean"])
            res["count_error"][c].append(s["count_error_mean"])
            res["ts_ts"][c] = s["vr_ts_ts_mean"]
    return res


# ------------------------------------------------------------------------------- Fig. 7 data


def time_course_data(cond: str, held: Sequence[EvalTrial], ds: Dataset, classes: Sequence[str]) -> dict[str, Any]:
    trs = [t for t in held if t.entry["condition"] == cond]
    end = max(float(t.entry["stim_end_s"]) - t.onset for t in trs)
    t0, t1 = -0.2, end + 0.4
    rates: dict[str, dict[str, tuple]] = {"TouchReal": {}, "TouchSim": {}}
    bin_s, smooth = 0.005, 0.01
    for cls in classes:
        centres, r_tr = stn.psth([t.tr[cls] for t in trs], t0, t1, bin_s, smooth)
        rates["TouchReal"][cls] = (r_tr.mean(0), r_tr.min(0), r_tr.max(0))
        per_rep = []
        for t in trs:
            trains = t.ts.get(cls, [])
            reps = t.ts_repeats.get(cls, 1)
            n_models = len(trains) // max(1, reps)
            for r in range(reps):
                _, rr = stn.psth(trains[r * n_models : (r + 1) * n_models], t0, t1, bin_s, smooth)
                per_rep.append(rr.mean(0))
        per_rep = np.array(per_rep) if per_rep else np.zeros((1, centres.size))
        rates["TouchSim"][cls] = (per_rep.mean(0), per_rep.min(0), per_rep.max(0))
    t_stim = np.arange(t0, t1, 1.0 / 1000.0)
    force = np.zeros_like(t_stim)
    depth = np.zeros_like(t_stim)
    for t in trs:
        if t.channels is not None:
            tt = (t.k0 + np.arange(t.channels.shape[0])) / OUT_FS_HZ - t.onset
            force += np.interp(t_stim, tt, t.channels[:, 0])
        trial = ds.load(t.entry)
        depth += np.interp(t_stim, trial.cmd_t - t.onset, trial.cmd_depth)
    return {
        "t": centres,
        "rates": rates,
        "t_stim": t_stim,
        "force": force / len(trs),
        "depth": depth / len(trs),
        "title": f"{cond}: {len(trs)} held-out TouchReal trial(s); TouchSim band = min-max over repeats (model mean)",
    }


# ------------------------------------------------------------------------------------ driver


def select_held_out(ds: Dataset, params: EncoderParams, mode: str = "auto") -> tuple[list[dict[str, Any]], list[dict[str, Any]], str]:
    """(evaluated ramp+sine entries, all ramp+sine entries, description).

    ``auto``: the fit's held-out trials (all trials for parameters fitted elsewhere); ``all``: every
    trial; ``train``: the fit's training half, for choosing fit settings without looking at the
    held-out trials."""
    from ..fitting.fit import FIT_PROTOCOLS, fitted_on_every_trial, params_split_seed, split_repeats

    if mode not in ("auto", "all", "train"):
        raise ValueError("split must be 'auto', 'all' or 'train'")
    entries = [e for e in ds.entries() if e["protocol"] in FIT_PROTOCOLS and e.get("reference")]
    if mode != "all" and fitted_on_every_trial(params, ds):
        return entries, entries, (f"all {len(entries)} ramp/sine trials: the fit TRAINED on every one (no held-out part; "
                                  "not a held-out result - evaluate a separate recording for that)")
    seed = params_split_seed(params, ds) if mode != "all" else None
    if seed is None:
        if mode == "train":
            raise ValueError("--split train needs parameters fitted on this dataset by `touchreal fit` (the split seed is in their provenance)")
        why = "requested" if mode == "all" else "the parameters were not fitted on this dataset by `touchreal fit`"
        return entries, entries, f"all {len(entries)} ramp/sine trials ({why})"
    train, held = split_repeats(entries, seed)
    if mode == "train":
        return train, entries, f"{len(train)} TRAINING ramp/sine trials of {len(entries)} (split seed {seed}; not a held-out result)"
    return held, entries, f"{len(held)} held-out ramp/sine trials of {len(entries)} (split seed {seed}, as recorded by the fit)"


def evaluate(dataset_dir: str | Path, params: EncoderParams, out_dir: str | Path, cfg: EvalConfig | None = None, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the whole evaluation; returns the metrics written to metrics.json."""
    from . import figures as fg

    cfg = cfg or EvalConfig()
    log = log or (lambda s: None)
    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ds = Dataset.open(dataset_dir)
    classes = [c for c in CLASSES if c in params.classes]
    held_e, all_e, split_note = select_held_out(ds, params, cfg.split)
    if not held_e:
        if all_e:
            raise ValueError(f"{dataset_dir}: the fit held out no trial (every condition has a single repeat); use --split all")
        raise ValueError(f"{dataset_dir}: no ramp/sine trials with reference spikes to evaluate")
    log(f"evaluating on {split_note}")
    held_ids = {e["id"] for e in held_e}
    all_trials = run_trials(ds, all_e, params, classes, keep_channels=held_ids, progress=cfg.progress, desc="ramp/sine")
    held = [t for t in all_trials if t.entry["id"] in held_ids]

    metrics: dict[str, Any] = {
        "dataset": str(ds.manifest.get("name", "")),
        "dataset_dir": str(Path(dataset_dir).resolve()),
        "evaluated_on": split_note,
        "n_held_out": len(held),
        "classes": classes,
        "params_provenance": params.provenance,
        "alignment": params.alignment.model_dump(),
        "vr_tau_ms": 1000.0 * cfg.vr_tau_s,
        "definitions": {
            "intra": "TouchSim-TouchSim: mean over conditions of the mean VR distance over all distinct pairs of TouchSim trains (repeats x models) of the condition's held-out trials",
            "inter": "TouchSim-TouchReal: mean over conditions of the mean VR distance over all (held-out TouchReal trial, TouchSim train) pairs",
            "ratio_inter_intra": "inter / intra",
            "ratio_inter_intra_with_trtr": "inter / mean(TS-TS, TR-TR), over conditions where TR-TR exists",
            "count_error": "mean over conditions (N_TS >= 1) of |N_TR - N_TS| / N_TS, whole-trial mean counts",
        },
        "figures": {},
    }
    figs = metrics["figures"]

    # Fig. 8 + counts
    log("VR distances ...")
    mapping = mapping_metrics(held, all_trials, classes, cfg.vr_tau_s)
    metrics["mapping"] = {c: mapping[c]["summary"] for c in classes}
    metrics["mapping_per_condition"] = {c: mapping[c]["rows"] for c in classes}
    ratios = {c: mapping[c]["summary"]["all"].get("ratio_inter_intra", np.nan) for c in classes}
    box = {c: {k: np.array([r[k] for r in mapping[c]["rows"]], float) for k in ("ts_ts", "tr_tr", "ts_tr")} for c in classes}
    figs["fig8"] = fg.fig8_vr_boxes(out / "fig8_vr_distance.png", box, ratios, 1000.0 * cfg.vr_tau_s).name

    # per-class latency, beside the fidelity
    lat_e = [t.entry for t in held if t.entry["protocol"] == "ramp"]
    fig7_first = sorted(lat_e, key=lambda e: e["condition"] != (cfg.ramp_condition or FIG7_PREFERRED))
    log("latency ...")
    metrics["latency"] = latency_table(params, [ds.load(e) for e in fig7_first[: cfg.latency_trials]])

    # Table 1
    metrics["channel_contribution_pct"] = channel_contributions(held, params, classes)

    # Fig. 7
    ramp_conds = sorted({t.entry["condition"] for t in held if t.entry["protocol"] == "ramp"})
    if ramp_conds:
        cond = cfg.ramp_condition or (FIG7_PREFERRED if FIG7_PREFERRED in ramp_conds else ramp_conds[0])
        if cond not in ramp_conds:
            raise ValueError(f"ramp condition {cond!r} has no held-out trial")
        figs["fig7"] = fg.fig7_time_courses(out / "fig7_time_courses.png", time_course_data(cond, held, ds, classes)).name
        metrics["fig7_condition"] = cond

    # spikes at the ramp's turning points (where the count error comes from)
    ramp_held = [t for t in held if tp.is_commanded_ramp(t.entry)]
    if ramp_held:
        metrics["turning_points"] = tp.turning_point_table(ramp_held, classes)
        if cfg.bound_jitters_ms:
            bound_classes = [c for c in BOUND_CLASSES if c in classes]
            metrics["missing_spike_bound"] = missing_spike_bound(held, bound_classes, cfg.vr_tau_s, cfg.bound_jitters_ms, cfg.seed)

    # Fig. 9, Tables 2-3
    sine = [t for t in held if t.entry["protocol"] == "sine"]
    fr_classes = [c for c in ("RA", "PC") if c in classes]
    if sine and fr_classes:
        fr = frequency_response(sine, fr_classes)
        metrics["frequency_response"] = fr
        curves = {c: {s: (fr[c]["curves"][s]["mean"], fr[c]["curves"][s]["ci_lo"], fr[c]["curves"][s]["ci_hi"]) for s in ("TouchSim", "TouchReal")} for c in fr_classes}
        figs["fig9"] = fg.fig9_frequency(out / "fig9_frequency_response.png", np.array(fr["freqs_hz"]), curves).name

    # Figs. 10-11
    if cfg.with_spatial:
        sp_e = [e for e in ds.entries() if e["protocol"] in ("spatial_ramp", "spatial_sine")]
        if sp_e:
            log(f"spatial scan: {len(sp_e)} trials ...")
            sp_trials = run_trials(ds, sp_e, params, classes, progress=cfg.progress, desc="spatial")
            spm = spatial_metrics(sp_trials, classes)
            _spatial_figures(out, spm, figs)
            metrics["spatial"] = _strip_private(spm)

    # Fig. 12
    if cfg.with_sweep:
        sweep_e = list(held_e)
        ramp_c = sorted({e["condition"] for e in sweep_e if e["protocol"] == "ramp"})
        if cfg.sweep_max_ramp_conditions is not None and len(ramp_c) > cfg.sweep_max_ramp_conditions:
            keep = set(np.random.default_rng(cfg.seed).choice(ramp_c, cfg.sweep_max_ramp_conditions, replace=False).tolist())
            sweep_e = [e for e in sweep_e if e["protocol"] != "ramp" or e["condition"] in keep]
        log(f"window sweep over {list(cfg.sweep_windows_ms)} ms on {len(sweep_e)} trials ...")
        sw = window_sweep(ds, sweep_e, params, classes, cfg)
        sw["n_trials"] = len(sweep_e)
        sw["ramp_conditions"] = "all" if cfg.sweep_max_ramp_conditions is None else min(cfg.sweep_max_ramp_conditions, len(ramp_c))
        metrics["window_sweep"] = sw
        figs["fig12"] = fg.fig12_window(out / "fig12_window_sweep.png", sw).name

    metrics["targets"] = check_targets(metrics, classes)
    metrics["seconds"] = round(time.perf_counter() - t_start, 1)
    (out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=1, allow_nan=True) + "\n")
    (out / "report.md").write_text(render_markdown(metrics))
    log(f"report written to {out} in {metrics['seconds']} s")
    return metrics


def _spatial_figures(out: Path, spm: dict[str, Any], figs: dict[str, str]) -> None:
    from . import figures as fg

    maps, radial, area, sweep, aniso = [], {}, {}, {}, {}
    for cls, res in spm.items():
        conds = res["conditions"]
        for c in conds:
            if "_map_tr" in c:
                x, y = sp.polar_to_xy(np.array(c["r"]), np.array(c["theta"]))
                maps.append({"title": f"{cls} TouchReal, {res['xlabel'].split(' ')[0]} {c['level']:g}", "map": c["_map_tr"], "x": x, "y": y})
        radial[cls] = [{"label": f"{c['level']:g}", "radii": c["radii"], "tr": c["radial_tr"], "ts": c["radial_ts"]} for c in conds]
        area[cls] = {"levels": res["levels"], "tr": [c["area_tr"] for c in conds], "ts": [c["area_ts"] for c in conds], "xlabel": res["xlabel"]}
        sweep[cls] = {"levels": [f"{v:g}" for v in res["levels"]], "thresholds": SWEEP_THRESHOLDS, "area": [c["area_sweep_tr"] for c in conds], "xlabel": res["xlabel"]}
        # polar profile averaged over conditions
        def avg(key):
            arr = np.array([c[key] for c in conds if len(c[key]) and np.all(np.isfinite(c[key]))], float)
            return arr.mean(0) if arr.size else np.full(len(conds[0]["angles"]) if conds else 0, np.nan)
        aniso[cls] = {
            "angles": conds[0]["angles"] if conds else [],
            "profile_tr": avg("profile_tr"),
            "profile_tr_std": avg("profile_tr_std"),
            "profile_ts": avg("profile_ts"),
            "profile_ts_std": avg("profile_ts_std"),
            "axis_tr": float(np.nanmean([c["axis_tr"] for c in conds])) if conds else np.nan,
            "levels": res["levels"],
            "ai2_tr": [c["ai2_tr"] for c in conds],
            "ai2_ts": [c["ai2_ts"] for c in conds],
            "xlabel": res["xlabel"],
        }
    if maps:
        figs["fig10_maps"] = fg.fig10_maps(out / "fig10_maps.png", maps).name
    if radial:
        figs["fig10_radial"] = fg.fig10_radial(out / "fig10_radial.png", radial).name
        figs["fig10_area"] = fg.fig10_area(out / "fig10_area.png", area, AREA_THRESHOLD).name
        figs["fig10_sweep"] = fg.fig10_sweep(out / "fig10_threshold_sweep.png", sweep).name
        figs["fig11"] = fg.fig11_anisotropy(out / "fig11_anisotropy.png", aniso).name


def _strip_private(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _strip_private(v) for k, v in d.items() if not str(k).startswith("_")}
    if isinstance(d, list):
        return [_strip_private(v) for v in d]
    return d


def _jsonable(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): _jsonable(v) for k, v in d.items() if not str(k).startswith("_")}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    if isinstance(d, np.ndarray):
        return _jsonable(d.tolist())
    if isinstance(d, (np.floating, float)):
        v = float(d)
        return v if np.isfinite(v) else None
    if isinstance(d, (np.integer,)):
        return int(d)
    if isinstance(d, np.bool_):
        return bool(d)
    return d


def check_targets(m: dict[str, Any], classes: Sequence[str]) -> dict[str, Any]:
    t: dict[str, Any] = {}
    for c in classes:
        s = m["mapping"][c]["all"]
        lim = TARGETS["vr_ratio_max"][c]
        t[f"vr_ratio_{c}"] = {"value": s.get("ratio_inter_intra"), "target": f"<= {lim}", "pass": bool(s.get("ratio_inter_intra", np.inf) <= lim)}
        ce = s.get("count_error_mean", np.inf)
        t[f"count_error_{c}"] = {"value": ce, "target": f"<= {TARGETS['count_error_max']}", "pass": bool(ce <= TARGETS["count_error_max"])}
    fr = m.get("frequency_response", {})
    if "RA" in fr:
        sh = fr["RA"]["shape"].get("TouchReal", {})
        t["RA_band_pass_peak_100Hz"] = {"value": sh.get("peak_hz"), "target": "band-pass, peak at 100 Hz", "pass": bool(sh.get("band_pass") and sh.get("peak_hz") == 100.0)}
    if "PC" in fr:
        sh = fr["PC"]["shape"].get("TouchReal", {})
        t["PC_rising"] = {"value": sh.get("spearman_rho"), "target": "Spearman rho >= 0.9 and rate(last) > rate(first)", "pass": bool(sh.get("rising"))}
    for c in ("RA", "PC"):
        if c in fr and "anova" in fr[c]:
            p = fr[c]["anova"]["source"]["p"]
            t[f"anova_source_{c}"] = {"value": p, "target": "p > 0.05", "pass": bool(p > TARGETS["anova_source_p_min"])}
    return t


def _f(v: Any, nd: int = 3) -> str:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not np.isfinite(v):
        return "n/a"
    if v == 0.0 and nd >= 3:
        return "< 1e-300" if v == 0.0 else "0"
    if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
        return f"{v:.2e}"
    return f"{v:.{nd}f}"


def render_markdown(m: dict[str, Any]) -> str:
    classes = m["classes"]
    L = [
        f"# TouchReal evaluation on `{m['dataset']}`",
        "",
        f"Data: simulated rig recordings (`{m['dataset_dir']}`). Evaluated on {m['evaluated_on']}. "
        f"Parameters: {json.dumps({k: m['params_provenance'].get(k) for k in ('fitted_by', 'dataset', 'split_method', 'split_seed', 'window_ms', 'class_window_ms') if k in m['params_provenance']})}.",
        "",
        "## Targets",
        "",
        "| check | value | target | result |",
        "|---|---|---|---|",
    ]
    for k, v in m["targets"].items():
        L.append(f"| {k} | {_f(v['value'])} | {v['target']} | {'PASS' if v['pass'] else 'FAIL'} |")
    lat = m.get("latency")
    if lat:
        al = m.get("alignment", {})
        L += ["", "## Per-class latency and fidelity", "",
              "Algorithmic = the online chain's bound on the time from a sensor sample to the emission of its spikes (the look-ahead "
              "of the class's source: its PVDF window, or the SingleTact alone); a spike's stamp is the sample's time plus the class "
              "delay (>= 0), so emission - stamp is at most algorithmic - delay. Measured = "
              "emission - stamp over the spikes of held-out ramp trials replayed in 1 ms chunks (median [90th percentile], spikes); "
              "emission - sample = that median + delay. A delay longer than the algorithmic latency stamps spikes after their emission. "
              f"Spikes are compared with the references at stamp - {_f(al.get('lag_ms'), 1)} ms (the rig's lag, `alignment`).", "",
              "| class | window [ms] | delay [ms] | algorithmic [ms] | bound on emission - stamp [ms] | measured emission - stamp [ms] | measured emission - sample [ms] | VR ratio | count error |",
              "|---|---|---|---|---|---|---|---|---|"]
        for c in classes:
            r, s = lat[c], m["mapping"][c]["all"]
            meas = (f"{_f(r['measured_median_ms'], 1)} [{_f(r['measured_p90_ms'], 1)}], {r['measured_spikes']}"
                    if r.get("measured_spikes") else "-")
            after = _f(r["measured_median_after_sample_ms"], 1) if r.get("measured_spikes") else "-"
            L.append(f"| {c} | {r['window_ms']:g} | {_f(r['delay_ms'], 1)} | {_f(r['algorithmic_ms'], 1)} | "
                     f"{_f(r['bound_emission_minus_stamp_ms'], 1)} | {meas} | {after} | {_f(s.get('ratio_inter_intra'))} | {_f(100 * s['count_error_mean'], 1)} % |")
    L += [
        "",
        "## Definitions",
        "",
        f"* VR distance: van Rossum, tau = {m['vr_tau_ms']:g} ms, normalised as `elephant` (distance 1 between an empty and a one-spike train); "
        "spike times relative to each trial's commanded onset.",
    ]
    L += [f"* {k}: {v}." for k, v in m["definitions"].items()]
    L += [
        "* TR-TR uses every recording of a condition (training recordings included): it measures the sensor pipeline's repeatability and uses no reference spikes.",
        "",
        "## Spike-train mapping (Fig. 8)",
        "",
        "![Fig. 8](" + m["figures"].get("fig8", "") + ")",
        "",
        "| class | protocol | conditions | TS-TS | TR-TR | TS-TR | inter/intra (TS-TS) | inter/intra (mean TS-TS, TR-TR) | count error (mean) | count bias |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in classes:
        for p, s in m["mapping"][c].items():
            if not s:
                continue
            L.append(
                f"| {c} | {p} | {s['n_conditions']} | {_f(s['vr_ts_ts_mean'])} | {_f(s['vr_tr_tr_mean'])} | {_f(s['vr_ts_tr_mean'])} | "
                f"{_f(s['ratio_inter_intra'])} | {_f(s['ratio_inter_intra_with_trtr'])} | {_f(100 * s['count_error_mean'], 1)} % | {_f(100 * s['count_bias'], 1)} % |"
            )
    L += ["", "Box plots show one value per condition (the condition's mean pair distance).", ""]
    if "fig7" in m["figures"]:
        L += ["## Ramp time courses (Fig. 7)", "", f"Condition `{m.get('fig7_condition')}`.", "", f"![Fig. 7]({m['figures']['fig7']})", ""]
    tps = m.get("turning_points")
    if tps:
        L += ["## Spikes at the ramp's turning points", "",
              "Each spike belongs to the nearest commanded turning point (onset, hold start, release start, release end; "
              "`peak` = hold start and release start of ramps without a hold). Spikes per train (TouchSim) or trial (TouchReal), "
              "mean |TR - TS| per trial, and TR's first spike minus TS's median first spike (median [quartiles], trials where both fired).", "",
              "| class | turning point | speed [mm/s] | trials | TS spikes | TR spikes | mean abs(TR - TS) | offset [ms] |", "|---|---|---|---|---|---|---|---|"]
        for c in classes:
            for r in tps.get(c, []):
                q = r["offset_ms_quartiles"]
                off = f"{q[1]:+.1f} [{q[0]:+.1f}, {q[2]:+.1f}]" if q else "-"
                L.append(f"| {c} | {r['event']} | {r['speed_mm_s']:g} | {r['n_trials']} | {_f(r['ts_spikes'], 2)} | {_f(r['tr_spikes'], 2)} | {_f(r['count_error'], 2)} | {off} |")
        L += [""]
    bound = m.get("missing_spike_bound")
    if bound:
        jit = [r["jitter_ms"] for r in next(iter(bound.values()))["as_fitted"]["filled"]]
        L += ["### Missing-spike bound", "",
              "The held-out VR ratio and count error if TouchReal also fired every spike it misses at the turning points "
              "(up to TouchSim's rounded mean count per window), placed at TouchSim's own median spike times plus Gaussian "
              "jitter of the given sd; sines and the spikes already fired are kept. An encoder can place such spikes "
              "no closer to TouchSim's than the sensor's own timing of the turning points allows (see the offsets above). "
              "`unbiased`: every ramp spike first moved by minus its turning point's median offset (an oracle).", "",
              "| class | base | base: VR ratio / count error | " + " | ".join(f"filled, jitter {j:g} ms" for j in jit) + " | added spikes per ramp trial |",
              "|---|---|---|" + "---|" * len(jit) + "---|"]
        for c, res in bound.items():
            for name, b in res.items():
                L.append(f"| {c} | {name} | {_f(b['ratio_inter_intra'])} / {_f(100 * b['count_error'], 1)} % | "
                         + " | ".join(f"{_f(r['ratio_inter_intra'])} / {_f(100 * r['count_error'], 1)} %" for r in b["filled"])
                         + f" | {_f(b['filled'][0]['added_per_ramp_trial'], 2)} |")
        L += [""]
    L += ["## Effective channel contribution (Table 1, eq. 11)", "", "| class | " + " | ".join(CHANNELS) + " |", "|---|" + "---|" * len(CHANNELS)]
    for c in classes:
        L.append(f"| {c} | " + " | ".join(f"{m['channel_contribution_pct'][c][ch]:.2f} %" for ch in CHANNELS) + " |")
    fr = m.get("frequency_response")
    if fr:
        L += ["", "## Frequency response (Fig. 9, Tables 2-3)", "", f"![Fig. 9]({m['figures'].get('fig9', '')})", ""]
        L += ["| class | source | " + " | ".join(f"{f:g} Hz" for f in fr["freqs_hz"]) + " | peak | Spearman rho |", "|---|---|" + "---|" * (len(fr["freqs_hz"]) + 2)]
        for c in [k for k in ("RA", "PC") if k in fr]:
            for s in ("TouchSim", "TouchReal"):
                cv = fr[c]["curves"][s]
                sh = fr[c]["shape"].get(s, {})
                cells = [f"{_f(mu, 1)} [{_f(lo, 1)}, {_f(hi, 1)}]" for mu, lo, hi in zip(cv["mean"], cv["ci_lo"], cv["ci_hi"])]
                L.append(f"| {c} | {s} | " + " | ".join(cells) + f" | {_f(sh.get('peak_hz'), 0)} Hz | {_f(sh.get('spearman_rho'), 2)} |")
        for i, c in enumerate([k for k in ("RA", "PC") if k in fr]):
            if "anova" not in fr[c]:
                continue
            L += ["", f"Table {2 + i}. Two-way ANOVA, {c} firing rate (Type II; observations: TouchSim {fr[c]['n_obs']['TouchSim']} trains, TouchReal {fr[c]['n_obs']['TouchReal']} trials)", "", "| effect | F | p | significance | balanced-design p |", "|---|---|---|---|---|"]
            for eff in ("frequency", "source", "interaction"):
                row = fr[c]["anova"][eff]
                bal = fr[c].get("anova_balanced", {}).get(eff, {})
                L.append(f"| {eff} | {_f(row['F'], 2)} | {_f(row['p'])} | {stats.significance(row['p'])} | {_f(bal.get('p'))} |")
    spm = m.get("spatial")
    if spm:
        L += ["", "## Receptive-field-like responses (Figs. 10-11)", ""]
        for k in ("fig10_maps", "fig10_radial", "fig10_area", "fig10_sweep", "fig11"):
            if k in m["figures"]:
                L += [f"![{k}]({m['figures'][k]})", ""]
        L += [f"| class | level | area >= {AREA_THRESHOLD:g} spikes TR [mm^2] | TS [mm^2] | AI_2 TR | AI_2 TS |", "|---|---|---|---|---|---|"]
        for c, res in spm.items():
            for cond in res["conditions"]:
                L.append(f"| {c} | {res['xlabel'].split(' ')[0]} {cond['level']:g} | {_f(cond['area_tr'], 1)} | {_f(cond['area_ts'], 1)} | {_f(cond['ai2_tr'])} | {_f(cond['ai2_ts'])} |")
        L += ["", "TouchSim's spatial reference has the afferent at the sensor centre; its maps are rotationally symmetric up to noise. "
              "Areas come from linear interpolation of the sampled positions inside the scanned disc. "
              "AI_2 averages every ring r > 0 with a non-zero response (as in the paper), so rings with one or two spikes in total "
              "(e.g. TouchSim at 0.3 mm off centre) give values near 1.", ""]
    sw = m.get("window_sweep")
    if sw:
        L += ["## Causal window sweep (Fig. 12)", "", f"![Fig. 12]({m['figures'].get('fig12', '')})", "",
              f"{sw['n_trials']} held-out trials ({sw['ramp_conditions']} ramp conditions + sines); class parameters fixed (not refitted per window).", "",
              "| window [ms] | " + " | ".join(f"VR {c}" for c in classes) + " | " + " | ".join(f"count err {c}" for c in classes) + " |",
              "|---|" + "---|" * (2 * len(classes))]
        for i, w in enumerate(sw["windows_ms"]):
            L.append(f"| {w:g} | " + " | ".join(_f(sw["vr"][c][i], 2) for c in classes) + " | " + " | ".join(f"{_f(100 * sw['count_error'][c][i], 1)} %" for c in classes) + " |")
    L += ["", f"Evaluation time: {m.get('seconds', 'n/a')} s.", ""]
    return "\n".join(L)
