"""Compare the simulated e-skin with the rig-v1 recordings: statistics table and figures.

    python -m touchreal.analysis.compare --shared DIR --out docs/img [--seed S] [--json FILE]

For a subset of rig-v1 trials, the same conditions are simulated (no reference spikes) and the
same statistics are computed on both: hold force vs depth, SingleTact baseline and noise, PVDF
noise floor and mains harmonics, sine PVDF amplitude per frequency, ramp timing and PVDF
transients, radial profiles, texture responses. Prints a markdown table (pasted into
docs/simulator.md) and writes ``simulator-comparison.png`` and ``simulator-traces.png`` to
``--out``. Nothing from the recordings is copied into the simulator: only these statistics were
used to choose a few physical constants (see :class:`~touchreal.simulator.eskin.SkinParams`).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from scipy import signal

from ..recording import Dataset, Trial
from ..settings import shared_dir
from ..simulator.simulate import Condition, conditions, simulate_trial

_NOTCH = np.vstack([signal.tf2sos(*signal.iirnotch(50.0 * h, 15.0, fs=2000.0)) for h in range(1, 9)])

Pair = tuple[dict[str, Any], Trial]


def _tone(x: np.ndarray, f: float, fs: float) -> float:
    """Amplitude of the ``f`` Hz component of ``x`` (single-bin DFT)."""
    x = np.asarray(x, float)
    tt = np.arange(x.size) / fs
    return float(2 * abs((x - x.mean()) @ np.exp(-2j * np.pi * f * tt)) / max(x.size, 1))


def _baseline(e: dict, tr: Trial) -> tuple[np.ndarray, np.ndarray]:
    return tr.st[tr.st_t < e["onset_s"]].astype(float), tr.pvdf[tr.pvdf_t < e["onset_s"] - 0.005].astype(float)


# ------------------------------------------------------------------------------------------------
# statistics (the same function on rig and simulated pairs)


def ramp_stats(pairs: list[Pair]) -> dict[str, Any]:
    hold = defaultdict(list)
    peak_up, peak_dn = defaultdict(list), defaultdict(list)
    delay_up, delay_dn = defaultdict(list), defaultdict(list)
    ratio = defaultdict(list)
    for e, tr in pairs:
        p, ev = e["params"], e["events"]
        st_t, st = tr.st_t, tr.st.astype(float)
        base = st[st_t < e["onset_s"]].mean()
        if p["hold_s"] >= 1.2:
            hold[p["depth_mm"]].append(st[(st_t > ev["release_start_s"] - 0.3) & (st_t < ev["release_start_s"])].mean() - base)
        if p["hold_s"] >= 0.6:
            f_hold = st[(st_t > ev["release_start_s"] - 0.1) & (st_t < ev["release_start_s"])].mean()
            up = np.flatnonzero((st_t > e["onset_s"]) & (st >= 0.5 * f_hold))
            dn = np.flatnonzero((st_t > ev["release_start_s"]) & (st <= 0.5 * f_hold))
            frac = 0.5 ** (1 / 1.78)  # depth fraction at half force
            if up.size:
                delay_up[p["v_up_mm_s"]].append(st_t[up[0]] - (e["onset_s"] + frac * p["depth_mm"] / p["v_up_mm_s"]))
            if dn.size:
                delay_dn[p["v_down_mm_s"]].append(st_t[dn[0]] - (ev["release_start_s"] + (1 - frac) * p["depth_mm"] / p["v_down_mm_s"]))
            pv = signal.sosfiltfilt(_NOTCH, tr.pvdf.astype(float))
            pt = tr.pvdf_t
            peak_up[p["v_up_mm_s"]].append(pv[(pt > e["onset_s"]) & (pt < ev["hold_start_s"] + 0.1)].max())
            peak_dn[p["v_down_mm_s"]].append(-pv[(pt > ev["release_start_s"]) & (pt < e["stim_end_s"] + 0.1)].min())
        else:
            ratio[(p["v_up_mm_s"], p["v_down_mm_s"])].append(st.max() - base)
    depths = sorted(hold)
    return {
        "hold_force_n": {d: (float(np.mean(hold[d])), float(np.std(hold[d]))) for d in depths},
        "press_delay_ms": {v: 1e3 * float(np.median(delay_up[v])) for v in sorted(delay_up)},
        "release_delay_ms": {v: 1e3 * float(np.median(delay_dn[v])) for v in sorted(delay_dn)},
        "pvdf_press_peak_v": {v: float(np.mean(peak_up[v])) for v in sorted(peak_up)},
        "pvdf_release_peak_v": {v: float(np.mean(peak_dn[v])) for v in sorted(peak_dn)},
        "hold0_peak_n": {f"{a:g}/{b:g}": float(np.mean(ratio[(a, b)])) for a, b in sorted(ratio)},
    }


def baseline_stats(pairs: list[Pair]) -> dict[str, Any]:
    st_off, st_sd, pv_rms, harm, asd = [], [], [], [], []
    for e, tr in pairs:
        st, pv = _baseline(e, tr)
        if st.size < 10 or pv.size < 400:
            continue
        st_off.append(st.mean())
        st_sd.append(st.std())
        seg = pv[:400]
        pv_rms.append(seg.std())
        harm.append([_tone(seg, 50.0 * h, 2000.0) for h in range(1, 9)])
        asd.append(np.sqrt(signal.welch(seg, fs=2000.0, nperseg=400)[1]))
    f = signal.welch(np.zeros(400), fs=2000.0, nperseg=400)[0]
    asd_m = np.sqrt(np.mean(np.square(asd), axis=0))
    floor = (f > 400) & (f < 990) & (np.abs(f - 50 * np.round(f / 50)) > 10)
    return {
        "st_offset_n": float(np.mean(st_off)),
        "st_noise_sd_n": float(np.median(st_sd)),
        "pvdf_rms_v": float(np.median(pv_rms)),
        "pvdf_floor_asd": float(np.median(asd_m[floor])),
        "pvdf_asd_10hz": float(asd_m[np.argmin(abs(f - 10))]),
        "mains_v": [float(x) for x in np.median(harm, axis=0)],
        "asd_f": f.tolist(),
        "asd": asd_m.tolist(),
    }


def sine_stats(pairs: list[Pair]) -> dict[str, Any]:
    amp, h2, st_pre, st_amp, st_mean = (defaultdict(list) for _ in range(5))
    for e, tr in pairs:
        f = e["params"]["freq_hz"]
        sel = (tr.pvdf_t > e["onset_s"] + 0.1) & (tr.pvdf_t < e["stim_end_s"] - 0.1)
        amp[f].append(_tone(tr.pvdf[sel], f, 2000.0))
        if 2 * f < 1000:
            h2[f].append(_tone(tr.pvdf[sel], 2 * f, 2000.0) / max(amp[f][-1], 1e-9))
        ss = (tr.st_t > e["onset_s"] + 0.1) & (tr.st_t < e["stim_end_s"] - 0.1)
        st_pre[f].append(tr.st[tr.st_t < e["onset_s"]].mean())
        st_mean[f].append(tr.st[ss].mean())
        st_amp[f].append(_tone(tr.st[ss], f, 100.0) if f < 50 else 0.0)
    fs = sorted(amp)
    return {
        "pvdf_amp_v": {f: float(np.mean(amp[f])) for f in fs},
        "pvdf_h2_rel": {f: float(np.mean(h2[f])) for f in fs if h2[f]},
        "st_preload_n": float(np.mean([np.mean(st_pre[f]) for f in fs])),
        "st_mean_during_n": {f: float(np.mean(st_mean[f])) for f in fs},
        "st_amp_10hz_n": float(np.mean(st_amp[10.0])) if 10.0 in st_amp else float("nan"),
    }


def spatial_stats(ramps: list[Pair], sines: list[Pair]) -> dict[str, Any]:
    st_r, pv_r = defaultdict(list), defaultdict(list)
    for e, tr in ramps:
        if e["params"]["depth_mm"] != 0.7:
            continue
        ev = e["events"]
        st = tr.st.astype(float)
        f = st[(tr.st_t > ev["release_start_s"] - 0.3) & (tr.st_t < ev["release_start_s"])].mean() - st[tr.st_t < e["onset_s"]].mean()
        st_r[e["offset_r_mm"]].append(f)
    for e, tr in sines:
        f = e["params"]["freq_hz"]
        sel = (tr.pvdf_t > e["onset_s"] + 0.1) & (tr.pvdf_t < e["stim_end_s"] - 0.1)
        pv_r[(f, e["offset_r_mm"])].append(_tone(tr.pvdf[sel], f, 2000.0))
    radii = sorted(st_r)
    freqs = sorted({f for f, _ in pv_r})
    return {
        "st_force_n_d0.7": {r: float(np.mean(st_r[r])) for r in radii},
        "pvdf_amp_v": {f: {r: float(np.mean(pv_r[(f, r)])) for r in sorted({r for g, r in pv_r if g == f})} for f in freqs},
    }


def texture_stats(pairs: list[Pair]) -> dict[str, Any]:
    rms, st_sd, fpk = defaultdict(list), defaultdict(list), defaultdict(list)
    for e, tr in pairs:
        s, ev = e["params"]["spacing_mm"], e["events"]
        sel = (tr.pvdf_t > ev["slide_start_s"] + 0.2) & (tr.pvdf_t < ev["slide_end_s"] - 0.1)
        x = tr.pvdf[sel].astype(float)
        rms[s].append(x.std())
        f, p = signal.welch(signal.sosfiltfilt(_NOTCH, x), fs=2000.0, nperseg=1024)
        fpk[s].append(f[np.argmax(p * (f > 4))])
        ss = (tr.st_t > ev["slide_start_s"] + 0.2) & (tr.st_t < ev["slide_end_s"] - 0.1)
        st_sd[s].append(tr.st[ss].std())
    sp = sorted(rms)
    return {
        "pvdf_rms_v": {s: float(np.mean(rms[s])) for s in sp},
        "pvdf_peak_hz": {s: float(np.median(fpk[s])) for s in sp},
        "st_sd_n": {s: float(np.mean(st_sd[s])) for s in sp},
    }


# ------------------------------------------------------------------------------------------------


def _rig_pairs(ds: Dataset, protocol: str, keep: Callable[[dict], bool] = lambda e: True) -> list[Pair]:
    return [(e, ds.load(e)) for e in ds.entries(protocol) if keep(e)]


def _sim_pairs(rig: list[Pair], by_name: dict[str, Condition], seed: int) -> list[Pair]:
    out = []
    for i, (e, _) in enumerate(rig):
        entry, trial = simulate_trial(by_name[e["condition"]], e["repeat"], e["id"], [seed, i], reference=False)
        out.append((entry, trial))
    return out


def collect(shared: Path, seed: int = 0, ramp_repeats: int = 1) -> dict[str, Any]:
    """Load rig-v1 subsets, simulate the same conditions, return statistics and example pairs."""
    ds = Dataset.open(Path(shared) / "datasets" / "rig-v1")
    names = {c.condition: c for p in ("ramp", "sine", "texture", "spatial_ramp", "spatial_sine") for c in conditions(p)}
    groups = {
        "ramp": _rig_pairs(ds, "ramp", lambda e: e["repeat"] < ramp_repeats),
        "sine": _rig_pairs(ds, "sine", lambda e: e["repeat"] < 10),
        "texture": _rig_pairs(ds, "texture", lambda e: e["repeat"] < 10),
        "spatial_ramp": _rig_pairs(ds, "spatial_ramp", lambda e: e["repeat"] == 0),
        "spatial_sine": _rig_pairs(ds, "spatial_sine", lambda e: e["repeat"] == 0),
    }
    result: dict[str, Any] = {"n_trials": {}}
    for source in ("rig", "sim"):
        g = groups if source == "rig" else {k: _sim_pairs(v, names, seed + j) for j, (k, v) in enumerate(groups.items())}
        result["n_trials"][source] = {k: len(v) for k, v in g.items()}
        result[source] = {
            "ramp": ramp_stats(g["ramp"]),
            "baseline": baseline_stats(g["ramp"] + g["texture"]),
            "sine": sine_stats(g["sine"]),
            "spatial": spatial_stats(g["spatial_ramp"], g["spatial_sine"]),
            "texture": texture_stats(g["texture"]),
        }
        result.setdefault("examples", {})[source] = {
            k: next((p for p in g[k2] if p[0]["condition"] == k), None)
            for k, k2 in (("ramp_d1.4_vu65_vd65_h0.6", "ramp"), ("sine_f100", "sine"), ("texture_s2.0", "texture"))
        }
    return result


def table(res: dict[str, Any]) -> str:
    """Markdown table of the headline statistics, rig-v1 vs simulator."""
    r, s = res["rig"], res["sim"]
    rows: list[tuple[str, str, str]] = []

    def add(name: str, a: float, b: float, fmt: str = "{:.3f}") -> None:
        rows.append((name, fmt.format(a), fmt.format(b)))

    for d, (m, _) in r["ramp"]["hold_force_n"].items():
        add(f"hold force at {d:g} mm (N)", m, s["ramp"]["hold_force_n"][d][0], "{:.2f}")
    for v in r["ramp"]["press_delay_ms"]:
        add(f"ST 50% delay, press {v:g} mm/s (ms)", r["ramp"]["press_delay_ms"][v], s["ramp"]["press_delay_ms"][v], "{:.0f}")
    for v in r["ramp"]["release_delay_ms"]:
        add(f"ST 50% delay, release {v:g} mm/s (ms)", r["ramp"]["release_delay_ms"][v], s["ramp"]["release_delay_ms"][v], "{:.0f}")
    for k in r["ramp"]["hold0_peak_n"]:
        if k in ("95/95", "8/8", "40/40"):
            add(f"ST peak, no hold, v {k} mm/s, mean over depths (N)", r["ramp"]["hold0_peak_n"][k], s["ramp"]["hold0_peak_n"][k], "{:.2f}")
    for v in r["ramp"]["pvdf_press_peak_v"]:
        add(f"PVDF press peak, {v:g} mm/s (V)", r["ramp"]["pvdf_press_peak_v"][v], s["ramp"]["pvdf_press_peak_v"][v])
    for v in r["ramp"]["pvdf_release_peak_v"]:
        add(f"PVDF release peak, {v:g} mm/s (V)", r["ramp"]["pvdf_release_peak_v"][v], s["ramp"]["pvdf_release_peak_v"][v])
    b, c = r["baseline"], s["baseline"]
    add("ST baseline offset (N)", b["st_offset_n"], c["st_offset_n"])
    add("ST baseline noise sd (N)", b["st_noise_sd_n"], c["st_noise_sd_n"], "{:.4f}")
    add("PVDF baseline rms (V)", b["pvdf_rms_v"], c["pvdf_rms_v"], "{:.4f}")
    add("PVDF noise floor 400-990 Hz (V/sqrt(Hz))", b["pvdf_floor_asd"], c["pvdf_floor_asd"], "{:.2e}")
    add("PVDF ASD at 10 Hz (V/sqrt(Hz))", b["pvdf_asd_10hz"], c["pvdf_asd_10hz"], "{:.2e}")
    for h in range(8):
        add(f"mains {50 * (h + 1)} Hz amplitude (mV)", 1e3 * b["mains_v"][h], 1e3 * c["mains_v"][h], "{:.2f}")
    for f in r["sine"]["pvdf_amp_v"]:
        add(f"sine {f:g} Hz: PVDF amplitude (V)", r["sine"]["pvdf_amp_v"][f], s["sine"]["pvdf_amp_v"][f])
    for f in r["sine"]["pvdf_h2_rel"]:
        add(f"sine {f:g} Hz: PVDF 2nd harmonic / fundamental", r["sine"]["pvdf_h2_rel"][f], s["sine"]["pvdf_h2_rel"][f])
    add("sine: ST preload (N)", r["sine"]["st_preload_n"], s["sine"]["st_preload_n"])
    add("sine 10 Hz: ST mean during burst (N)", r["sine"]["st_mean_during_n"][10.0], s["sine"]["st_mean_during_n"][10.0])
    add("sine 10 Hz: ST amplitude (N)", r["sine"]["st_amp_10hz_n"], s["sine"]["st_amp_10hz_n"])
    for rad, v in r["spatial"]["st_force_n_d0.7"].items():
        if rad <= 8:
            add(f"spatial ramp 0.7 mm, r = {rad:g} mm: ST force (N)", v, s["spatial"]["st_force_n_d0.7"][rad])
    for f, prof in r["spatial"]["pvdf_amp_v"].items():
        for rad, v in prof.items():
            if rad in (0, 4, 8, 10, 12):
                add(f"spatial sine {f:g} Hz, r = {rad:g} mm: PVDF amplitude (V)", v, s["spatial"]["pvdf_amp_v"][f][rad], "{:.4f}")
    for sp in r["texture"]["pvdf_rms_v"]:
        add(f"texture {sp:g} mm: PVDF rms (V)", r["texture"]["pvdf_rms_v"][sp], s["texture"]["pvdf_rms_v"][sp], "{:.4f}")
        add(f"texture {sp:g} mm: PVDF spectral peak (Hz)", r["texture"]["pvdf_peak_hz"][sp], s["texture"]["pvdf_peak_hz"][sp], "{:.1f}")
        add(f"texture {sp:g} mm: ST sd during slide (N)", r["texture"]["st_sd_n"][sp], s["texture"]["st_sd_n"][sp], "{:.3f}")
    lines = ["| statistic | rig-v1 | simulator |", "|---|---:|---:|"] + [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(lines)


def figures(res: dict[str, Any], out: Path) -> list[Path]:
    """Write the comparison and example-trace figures (PNG) to ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    r, s = res["rig"], res["sim"]
    style = {"rig": dict(color="k", marker="o", label="rig-v1"), "sim": dict(color="tab:orange", marker="s", ls="--", label="simulator")}
    fig, ax = plt.subplots(2, 3, figsize=(14, 8))
    for src, st in (("rig", r), ("sim", s)):
        hf = st["ramp"]["hold_force_n"]
        ax[0, 0].errorbar(list(hf), [m for m, _ in hf.values()], [sd for _, sd in hf.values()], capsize=3, **style[src])
        b = st["baseline"]
        ax[0, 1].semilogy(b["asd_f"], b["asd"], color=style[src]["color"], ls=style[src].get("ls", "-"), label=style[src]["label"])
        sa = st["sine"]["pvdf_amp_v"]
        ax[0, 2].plot(list(sa), list(sa.values()), **style[src])
        sr = st["spatial"]["st_force_n_d0.7"]
        ax[1, 0].plot(list(sr), np.array(list(sr.values())) / max(sr[0.0], 1e-9), **{**style[src], "label": f"ST ramp 0.7 mm ({src})"})
        for f, mk in zip(st["spatial"]["pvdf_amp_v"], ("^", "v")):
            prof = st["spatial"]["pvdf_amp_v"][f]
            ax[1, 0].plot(list(prof), np.array(list(prof.values())) / prof[0.0], color=style[src]["color"], marker=mk,
                          ls=style[src].get("ls", "-"), alpha=0.6, label=f"PVDF {f:g} Hz ({src})")
        pu = st["ramp"]["pvdf_press_peak_v"]
        pd = st["ramp"]["pvdf_release_peak_v"]
        ax[1, 1].plot(list(pu), list(pu.values()), **{**style[src], "label": f"press ({src})"})
        ax[1, 1].plot(list(pd), list(pd.values()), color=style[src]["color"], marker="x", ls=":", label=f"release ({src})")
        tx = st["texture"]["pvdf_rms_v"]
        ts = st["texture"]["st_sd_n"]
        ax[1, 2].plot(list(tx), list(tx.values()), **{**style[src], "label": f"PVDF rms V ({src})"})
        ax[1, 2].plot(list(ts), list(ts.values()), color=style[src]["color"], marker="d", ls=":", label=f"ST sd N ({src})")
    titles = [
        ("hold force vs depth (ramp, hold >= 1.2 s)", "depth (mm)", "force (N)"),
        ("PVDF baseline amplitude spectral density", "frequency (Hz)", "V/sqrt(Hz)"),
        ("sine: PVDF amplitude at the drive frequency", "frequency (Hz)", "amplitude (V)"),
        ("radial profiles (normalised at r = 0)", "offset r (mm)", "relative response"),
        ("PVDF ramp transients (notched), all depths", "velocity (mm/s)", "peak |V|"),
        ("texture slides", "tooth spacing (mm)", "V or N"),
    ]
    for a, (t, xl, yl) in zip(ax.ravel(), titles):
        a.set_title(t, fontsize=10)
        a.set_xlabel(xl)
        a.set_ylabel(yl)
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    ax[0, 2].set_ylim(0, None)
    fig.suptitle("Simulated e-skin vs rig-v1 (simulated rig recordings): same conditions, same statistics")
    fig.tight_layout()
    p1 = out / "simulator-comparison.png"
    fig.savefig(p1, dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(3, 2, figsize=(14, 9))
    for col, key in enumerate(("ramp_d1.4_vu65_vd65_h0.6", "sine_f100", "texture_s2.0")):
        for src in ("rig", "sim"):
            pair = res["examples"][src][key]
            if pair is None:
                continue
            e, tr = pair
            t0 = e["onset_s"]
            ax[col, 0].plot(tr.st_t - t0, tr.st, color=style[src]["color"], label=style[src]["label"])
            ax[col, 1].plot(tr.pvdf_t - t0, tr.pvdf, color=style[src]["color"], lw=0.6, alpha=0.8, label=style[src]["label"])
        ax[col, 0].set_title(f"{key}: SingleTact (N)", fontsize=10)
        ax[col, 1].set_title(f"{key}: PVDF (V)", fontsize=10)
        for a in ax[col]:
            a.set_xlabel("time from commanded onset (s)")
            a.grid(alpha=0.3)
            a.legend(fontsize=7)
    fig.tight_layout()
    p2 = out / "simulator-traces.png"
    fig.savefig(p2, dpi=80)
    plt.close(fig)
    return [p1, p2]


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items() if k != "examples"}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m touchreal.analysis.compare", description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=None, help="shared data folder (default: TOUCHREAL_SHARED or ../shared)")
    ap.add_argument("--out", type=Path, default=Path("docs/img"), help="folder for the PNG figures")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated trials")
    ap.add_argument("--json", type=Path, default=None, help="also write all statistics as JSON here")
    args = ap.parse_args(list(argv) if argv is not None else None)
    shared = args.shared or shared_dir()
    if not (shared / "datasets" / "rig-v1" / "manifest.json").is_file():
        print(f"compare: no rig-v1 dataset under {shared}", file=sys.stderr)
        return 2
    res = collect(shared, seed=args.seed)
    print(table(res))
    for p in figures(res, args.out):
        print(f"wrote {p}")
    if args.json:
        args.json.write_text(json.dumps(_jsonable(res), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
