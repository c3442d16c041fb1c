"""``touchreal evaluate``: reproduce the paper's evaluation (section 3) on a dataset's held-out trials.

Writes ``report.md``, ``metrics.json`` and PNG figures into the report folder. Definitions (also
printed into the report):

* **Held-out trials.** If the parameter file was fitted by ``touchreal fit`` on this dataset (same
  manifest name, provenance carries the split seed), the ramp and sine trials the fit did not use
  (:func:`touchreal.splits.split_repeats`); otherwise every ramp and sine trial. Spatial
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..params import EncoderParams
from ..recording import Dataset
from ..settings import CLASSES
from . import turning_points as tp
from .latency import latency_table
from .metrics import (BOUND_CLASSES, BOUND_JITTERS_MS, SWEEP_WINDOWS_MS, VR_TAU_S, channel_contributions, check_targets,
                      frequency_response, mapping_metrics, missing_spike_bound, spatial_metrics, time_course_data,
                      window_sweep)
from .render import jsonable, render_markdown, spatial_figures, strip_private
from .trials import run_trials, select_held_out

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
            spatial_figures(out, spm, figs)
            metrics["spatial"] = strip_private(spm)

    # Fig. 12
    if cfg.with_sweep:
        sweep_e = list(held_e)
        ramp_c = sorted({e["condition"] for e in sweep_e if e["protocol"] == "ramp"})
        if cfg.sweep_max_ramp_conditions is not None and len(ramp_c) > cfg.sweep_max_ramp_conditions:
            keep = set(np.random.default_rng(cfg.seed).choice(ramp_c, cfg.sweep_max_ramp_conditions, replace=False).tolist())
            sweep_e = [e for e in sweep_e if e["protocol"] != "ramp" or e["condition"] in keep]
        log(f"window sweep over {list(cfg.sweep_windows_ms)} ms on {len(sweep_e)} trials ...")
        sw = window_sweep(ds, sweep_e, params, classes, cfg.sweep_windows_ms, cfg.vr_tau_s, cfg.progress)
        sw["n_trials"] = len(sweep_e)
        sw["ramp_conditions"] = "all" if cfg.sweep_max_ramp_conditions is None else min(cfg.sweep_max_ramp_conditions, len(ramp_c))
        metrics["window_sweep"] = sw
        figs["fig12"] = fg.fig12_window(out / "fig12_window_sweep.png", sw).name

    metrics["targets"] = check_targets(metrics, classes)
    metrics["seconds"] = round(time.perf_counter() - t_start, 1)
    (out / "metrics.json").write_text(json.dumps(jsonable(metrics), indent=1, allow_nan=True) + "\n")
    (out / "report.md").write_text(render_markdown(metrics))
    log(f"report written to {out} in {metrics['seconds']} s")
    return metrics
