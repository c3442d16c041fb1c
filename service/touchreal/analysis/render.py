"""Rendering of the evaluation: ``report.md``, the spatial figures' data and JSON-safe metrics."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..settings import CHANNELS
from . import spatial as sp
from . import stats
from .metrics import AREA_THRESHOLD, SWEEP_THRESHOLDS


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


def spatial_figures(out: Path, spm: dict[str, Any], figs: dict[str, str]) -> None:
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


def strip_private(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: strip_private(v) for k, v in d.items() if not str(k).startswith("_")}
    if isinstance(d, list):
        return [strip_private(v) for v in d]
    return d


def jsonable(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): jsonable(v) for k, v in d.items() if not str(k).startswith("_")}
    if isinstance(d, (list, tuple)):
        return [jsonable(v) for v in d]
    if isinstance(d, np.ndarray):
        return jsonable(d.tolist())
    if isinstance(d, (np.floating, float)):
        v = float(d)
        return v if np.isfinite(v) else None
    if isinstance(d, (np.integer,)):
        return int(d)
    if isinstance(d, np.bool_):
        return bool(d)
    return d
