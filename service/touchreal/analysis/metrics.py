"""The evaluation's metrics (paper section 3): VR distances and counts per condition, the
missing-spike bound, channel contributions, the frequency response, the spatial maps, the window
sweep, Fig. 7's time courses and the pass/fail targets. Pure functions of encoded trials."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..encoding.encoder import channel_currents
from ..params import EncoderParams
from ..recording import Dataset
from ..settings import CHANNELS, OUT_FS_HZ
from . import spatial as sp
from . import spiketrains as stn
from . import stats
from . import turning_points as tp
from .trials import EvalTrial, by_condition, run_trials

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


def mapping_metrics(
    held: Sequence[EvalTrial], all_trials: Sequence[EvalTrial], classes: Sequence[str], tau_s: float, ts_ts_cache: dict[tuple[str, str], float] | None = None
) -> dict[str, Any]:
    """Per class: per-condition mean VR distances and spike counts, and their summaries.

    ``ts_ts_cache`` ((class, condition) -> mean TS-TS distance) is filled and reused by calls on
    the same held-out trials, whose TouchSim trains do not change."""
    held_c = by_condition(held)
    all_c = by_condition(all_trials)
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


def window_sweep(
    ds: Dataset, entries: Sequence[dict[str, Any]], params: EncoderParams, classes: Sequence[str],
    windows_ms: Sequence[float], vr_tau_s: float = VR_TAU_S, progress: bool = False,
) -> dict[str, Any]:
    """Mean TS-TR VR distance and spike-count error against the causal PVDF window, with the
    fitted class parameters held fixed (no refit per window; the gate thresholds follow the
    calibrated noise spectrum for each window length)."""
    res: dict[str, Any] = {"windows_ms": list(windows_ms), "vr": {c: [] for c in classes}, "count_error": {c: [] for c in classes}, "ts_ts": {}}
    for w in windows_ms:
        trials = run_trials(ds, entries, params, classes, window_ms=w, progress=progress, desc=f"window {w:g} ms")
        m = mapping_metrics(trials, trials, classes, vr_tau_s)
        for c in classes:
            s = m[c]["summary"]["all"]
            res["vr"][c].append(s["vr_ts_tr_mean"])
            res["count_error"][c].append(s["count_error_mean"])
            res["ts_ts"][c] = s["vr_ts_ts_mean"]
    return res


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
