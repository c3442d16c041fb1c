"""Fit the encoder to a dataset's TouchSim reference spike trains (paper section 2.4).

Steps of :func:`fit_dataset`:

1. **Split** the ramp and sine trials by repeat (:mod:`.split`): within every condition the
   repeats are shuffled with the seed and the first half trains, the rest is held out. Validation
   never sees a training trial (nor its reference spikes). The split is recorded in the parameter
   file's provenance so ``touchreal evaluate`` can use exactly the held-out trials. With
   ``holdout=False`` every trial trains and nothing is held out (for a separate test recording).
2. **Calibrate** the PVDF stage (mains harmonics + spectral gate) on the contact-free baselines of
   the training trials (PVDF samples before ``onset_s``), and measure the build's contact SNR on the
   training ramps: below ``cfg.weak_signal_snr`` the gate and the sine count weights not given are
   the weak-signal ones, and below ``cfg.film_limited_snr`` PC's input high-pass and refinement
   count margin not given are the film-limited ones (:meth:`FitConfig.for_snr`). Measure the
   SingleTact's noise on the same baselines: above ``cfg.noisy_st_noise_n`` SA1 also searches from
   its saturated start and restarts, where not told otherwise (:meth:`FitConfig.for_singletact`).
3. **Preprocess** every trial once per distinct causal PVDF window of the fitted classes (:mod:`.trials`;
   channels do not depend on the class parameters; each class is fitted on its own window's
   channels) and keep the 5 kHz channels in memory.
4. Per class, **CMA-ES** (:mod:`.search`) in the normalised space of :mod:`.space`, minimising the
   objective of :mod:`.objective` over all training trials; each generation is one LIF population
   per trial (the candidates are the neurons of one population), evaluated by an
   :class:`~.executor.Executor` (forked worker processes, or Dask workers). The classes, and each
   class's restarts, search side by side so that every worker stays busy; every run has its own
   random stream, so the result does not depend on how they interleave.
5. Score the best candidate on the training and held-out trials; write everything into
   :class:`EncoderParams` with provenance.

Spike times enter the objective on the reference clock (stamp minus an alignment) and relative to
each trial's commanded onset (``onset_s``), so trials of one condition share a clock. The search
runs at an alignment of :data:`SEARCH_LAG_MS`, so a class may lead the reference by up to 250 ms
(the sensor's lag behind the commanded stimulus); the file records the smallest alignment that keeps
every class delay >= 0 (the class with the largest lead gets delay 0), kept classes of ``init``
re-expressed on it with the same reference-clock spikes. The fitter runs exactly the product
encoder's code, so a fitted parameter set behaves in the service as it did in the fit.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..params import EncoderParams, PreprocessParams, ReferenceAlignment
from ..recording import Dataset
from .calibration import calibrate_pvdf, contact_snr, singletact_noise
from .config import FitConfig, parse_stage_key, stage_key
from .executor import ExecutorFactory, FitSource, FitState, LocalExecutor
from .objective import ReferenceSet, evaluate_loss
from .search import ClassFit, search_and_refine
from .space import INITIAL_WEIGHTS, ParamSpace, touchsim_class_defaults
# fitted_on_every_trial and params_split_seed: the evaluation and the decoders read a file's split through this module
from .split import FIT_PROTOCOLS, NO_SPLIT_METHOD, SPLIT_METHOD, fitted_on_every_trial, params_split_seed, split_repeats  # noqa: F401
from .trials import TrialSet, baseline_segments, build_trial_set, channel_scale, estimate_lag_s, simulate

#: Alignment (ms) the search runs at: class delays of 0-500 ms then span reference-clock delays of
#: -250 ... +250 ms. The written file gets the smallest alignment that keeps every delay >= 0.
SEARCH_LAG_MS = 250.0


@dataclass
class FitResult:
    params: EncoderParams
    classes: dict[str, ClassFit]
    seconds: float
    timings: dict[str, float]
    n_train: int
    n_validation: int


@dataclass
class Prepared:
    """A fit's data before optimisation (:func:`prepare`): the opened dataset, its split, the
    calibrated preprocessing, the evaluation state, the measured rig lag and the step timings."""

    ds: Dataset
    train_e: list[dict[str, Any]]
    val_e: list[dict[str, Any]]
    cfg: FitConfig  #: the source's, with the gate factor and sine count weights chosen for the build
    pre: PreprocessParams
    n_baselines: int
    contact_snr: float | None  #: the PVDF contact SNR of the training ramps (None without ramps)
    st_noise_n: float | None  #: the SingleTact's sample noise (N RMS) on the baselines (None without them)
    state: FitState
    rig_lag_ms: float  #: the SingleTact's rise after the commanded onset (the search runs at SEARCH_LAG_MS)
    timings: dict[str, float]


def prepare(source: FitSource, log: Callable[[str], None] | None = None) -> Prepared:
    """Split, calibrate, preprocess and align (steps 1-3 of the fit); deterministic, so every Dask
    worker that runs it on the same source holds the same state as the driver."""
    cfg, init, dataset_dir = source.cfg, source.init, source.dataset_dir
    log = log or (lambda s: None)
    timings: dict[str, float] = {}
    ds = Dataset.open(dataset_dir)
    entries = [e for e in ds.entries() if e["protocol"] in FIT_PROTOCOLS and e.get("reference")]
    if not entries:
        raise ValueError(f"{dataset_dir}: no ramp or sine trials with reference spike trains")
    train_e, val_e = split_repeats(entries, cfg.seed) if cfg.holdout else (list(entries), [])
    if cfg.max_ramp_conditions is not None:
        conds = sorted({e["condition"] for e in train_e if e["protocol"] == "ramp"})
        if len(conds) > cfg.max_ramp_conditions:
            keep = set(np.random.default_rng(cfg.seed).choice(conds, cfg.max_ramp_conditions, replace=False).tolist())
            train_e = [e for e in train_e if e["protocol"] != "ramp" or e["condition"] in keep]
    log(f"split: {len(train_e)} training / {len(val_e)} held-out trials" + (f" (seed {cfg.seed})" if cfg.holdout else " (no held-out part)"))

    t = time.perf_counter()
    loaded = {e["id"]: ds.load(e) for e in train_e}
    base = init.preprocess if init is not None else PreprocessParams()
    segments = baseline_segments(ds, train_e, loaded=loaded)
    pre = calibrate_pvdf(segments, base.model_copy(update={"window_ms": float(cfg.window_ms)}))
    ramps = [(loaded[e["id"]], float(e["onset_s"])) for e in train_e if e["protocol"] == "ramp"]
    snr = contact_snr([r.pvdf for r, _ in ramps], [int(np.searchsorted(r.pvdf_t, onset)) for r, onset in ramps], pre)
    cfg = cfg.for_snr(snr)
    pre = pre.model_copy(update={"gate": pre.gate.model_copy(update={"factor": cfg.gate_factor})})
    timings["calibrate_s"] = time.perf_counter() - t
    log(f"PVDF calibration on {len(segments)} contact-free baselines: mains {pre.mains_hz:g} Hz, notch harmonics {pre.notch_harmonics}; "
        f"contact SNR {'-' if snr is None else f'{snr:.0f}'}" + (f" < {cfg.weak_signal_snr:g} (weak signal)" if cfg.weak_signal(snr) else "")
        + f": gate on {len(pre.gate.freqs_hz)} bins at {pre.gate.factor:g} x the noise"
        + (f", refinement sine count weights {cfg.refine_sine_count_weights}" if cfg.refine_sine_count_weights else "")
        + (f"; below {cfg.film_limited_snr:g} (film-limited)" if cfg.film_limited(snr) else "")
        + (f", input high-pass {cfg.highpass_hz} Hz" if cfg.highpass_hz else "")
        + (f", refinement count margins {cfg.refine_count_margins}" if cfg.refine_count_margins else ""))
    st_noise = singletact_noise(baseline_segments(ds, train_e, loaded=loaded, channel="st"))
    cfg = cfg.for_singletact(st_noise)
    log(f"SingleTact noise {'-' if st_noise is None else f'{1000.0 * st_noise:.1f} mN'}"
        + (f" > {1000.0 * cfg.noisy_st_noise_n:g} mN (noisy)" if cfg.noisy_singletact(st_noise) else "")
        + f": restarts {({c: cfg.restarts_of(c) for c in cfg.classes if cfg.restarts_of(c)}) or 'none'}, saturated start "
        + (",".join(c for c in cfg.classes if cfg.saturated(c)) or "none"))

    t = time.perf_counter()
    windows = sorted({cfg.window_of(c) for c in cfg.classes})
    trainsets: dict[float, TrialSet] = {}
    for w in windows:  # one preprocessing per distinct window
        trainsets[w] = build_trial_set(ds, train_e, pre.model_copy(update={"window_ms": w}), cfg.classes, loaded)
    del loaded
    train = {c: trainsets[cfg.window_of(c)] for c in cfg.classes}
    timings["preprocess_s"] = time.perf_counter() - t
    first = trainsets[windows[0]]
    rig_lag_ms = round(1000.0 * estimate_lag_s(first.trials), 3)
    lag_s = SEARCH_LAG_MS / 1000.0  # the search's alignment; the file gets the smallest that keeps every delay >= 0
    log(f"preprocessed at {windows} ms in {timings['preprocess_s']:.1f} s; channel scale "
        f"{np.round(channel_scale(first.trials), 4).tolist()}; rig lag {rig_lag_ms:.1f} ms (SingleTact rise after the commanded onset)")

    spaces = {}
    for c in cfg.classes:  # an input-stage class's weights are normalised behind its start cutoff
        lp0 = touchsim_class_defaults()[c]["lowpass_hz"] if c in cfg.input_stage_classes else None
        spaces[c] = ParamSpace.for_class(c, channel_scale(train[c].trials, lp0), input_stage=lp0 is not None,
                                         pvdf=c not in cfg.no_pvdf_classes, excitatory=c in cfg.excitatory_classes,
                                         highpass_hz=cfg.highpass_hz.get(c))
    for c in cfg.refined():  # a refinement evaluates on its class's trials and space
        spaces[stage_key(c, True)], train[stage_key(c, True)] = spaces[c], train[c]
    refs = {key: _references(train[key], key, cfg) for key in train}
    state = FitState(spaces=spaces, refs=refs, train=train, objectives={key: cfg.objective_of(key) for key in refs}, lag_s=lag_s)
    return Prepared(ds, train_e, val_e, cfg, pre, len(segments), snr, st_noise, state, rig_lag_ms, timings)


def _references(tset: TrialSet, key: str, cfg: FitConfig) -> ReferenceSet:
    """The reference set of a class's search (``key`` = the class: its segmented count if listed) or
    of its refinement (whole-trial counts, its VR-normalised distance if listed)."""
    cls, refinement = parse_stage_key(key)
    return tset.reference_set(cls, cfg.objective.kernel_tau_s, cfg.max_refs_per_condition, cfg.sine_weight,
                              segmented_count=not refinement and cls in cfg.segmented_count_classes,
                              vr_normalised=refinement and cls in cfg.vr_distance_classes,
                              sine_count_weight=(cfg.refine_sine_count_weights or {}).get(cls) if refinement else None)


def fit_dataset(
    dataset_dir: str | os.PathLike,
    cfg: FitConfig | None = None,
    init: EncoderParams | None = None,
    log: Callable[[str], None] | None = None,
    executor: ExecutorFactory | None = None,
) -> FitResult:
    """Fit every class of ``cfg.classes`` on the dataset's ramp + sine training trials, each class
    at its own causal PVDF window (``cfg.window_of``). ``executor`` makes the candidate evaluator
    (default :meth:`LocalExecutor.factory` with ``cfg.workers``; Dask: ``touchreal.fitting.dask_executor``)."""
    cfg = cfg or FitConfig()
    log = log or (lambda s: None)
    t_all = time.perf_counter()
    source = FitSource(str(dataset_dir), cfg, init)
    prep = prepare(source, log)
    cfg = prep.cfg
    ds, val_e, pre, timings, rig_lag_ms = prep.ds, prep.val_e, prep.pre, prep.timings, prep.rig_lag_ms
    name = str(ds.manifest.get("name", ""))
    spaces, refs, train, lag_s = prep.state.spaces, prep.state.refs, prep.state.train, prep.state.lag_s
    first = train[min(cfg.classes, key=cfg.window_of)]  # the smallest window's trial set (counts are the same in all)
    t = time.perf_counter()
    evaluator = (executor or LocalExecutor.factory(cfg.workers))(source, prep.state)
    timings["executor_start_s"] = time.perf_counter() - t  # Dask: every worker has loaded and preprocessed the dataset
    jobs = {}
    for position, cls in enumerate(cfg.classes):
        sp = spaces[cls]
        d0 = SEARCH_LAG_MS - rig_lag_ms  # spikes start aligned with the SingleTact's rise
        if init is not None and cls in init.classes:
            start = init.classes[cls]
            d0 = start.delay_ms - init.alignment.lag_ms + SEARCH_LAG_MS  # the same reference-clock spikes
            starts = [sp.clip(sp.encode(start.model_copy(update={"delay_ms": d0})))]
        else:
            starts = [sp.initial(d0, v) for v in range(len(INITIAL_WEIGHTS[cls]))]
        jobs[cls] = (cls, sp, evaluator, cfg, starts, d0, position)
    try:  # every class searches at once, so the workers never wait for one class's next generation
        with ThreadPoolExecutor(len(jobs), thread_name_prefix="fit") as pool:
            futures = {cls: pool.submit(search_and_refine, *job) for cls, job in jobs.items()}
            fits: dict[str, ClassFit] = {cls: f.result() for cls, f in futures.items()}
    finally:
        evaluator.close()

    t = time.perf_counter()
    val: dict[float, TrialSet] = {}
    for cls, f in fits.items():  # scored on the objective of the class's last stage
        key = stage_key(cls, f.search is not None)
        f.params = f.params.model_copy(update={"window_ms": None if cfg.window_of(cls) == pre.window_ms else cfg.window_of(cls)})
        f.train = evaluate_loss(simulate(train[cls].trials, [f.params], lag_s)[0], train[cls].cond_index, refs[key], cfg.objective_of(key))
        if val_e:
            w = cfg.window_of(cls)
            if w not in val:
                val[w] = build_trial_set(ds, val_e, pre.model_copy(update={"window_ms": w}), cfg.classes)
            f.validation = evaluate_loss(simulate(val[w].trials, [f.params], lag_s)[0], val[w].cond_index, _references(val[w], key, cfg),
                                         cfg.objective_of(key))
    timings["score_s"] = time.perf_counter() - t
    seconds = time.perf_counter() - t_all

    # every class's delay on the reference clock (< 0: it leads the stamp); kept classes keep their window
    lead_ms: dict[str, float] = {c: f.params.delay_ms - SEARCH_LAG_MS for c, f in fits.items()}
    classes = {c: f.params for c, f in fits.items()}
    if init is not None:
        for c, cp in init.classes.items():
            if c not in fits:
                own = init.window_ms(c)
                classes[c] = cp.model_copy(update={"window_ms": None if own == pre.window_ms else own})
                lead_ms[c] = cp.delay_ms - init.alignment.lag_ms
    lag_ms = max(0.0, -min(lead_ms.values()))  # the smallest alignment with every delay >= 0
    classes = {c: cp.model_copy(update={"delay_ms": max(0.0, lead_ms[c] + lag_ms)}) for c, cp in classes.items()}
    for c, f in fits.items():
        f.params = classes[c]
    prov: dict[str, Any] = {
        "fitted_by": "touchreal fit",
        "dataset": name,
        "dataset_dir": str(ds.root.resolve()),
        "protocols": list(FIT_PROTOCOLS),
        "split_method": SPLIT_METHOD if cfg.holdout else NO_SPLIT_METHOD,
        "split_seed": int(cfg.seed),
        "n_train_trials": len(first.trials),
        "n_validation_trials": len(val_e),
        "max_ramp_conditions": cfg.max_ramp_conditions if cfg.max_ramp_conditions is not None else "all",
        "window_ms": float(cfg.window_ms),
        "rig_lag_ms": rig_lag_ms,
        "class_window_ms": {c: cfg.window_of(c) for c in cfg.classes},
        "calibration_baselines": prep.n_baselines,
        "contact_snr": None if prep.contact_snr is None else round(prep.contact_snr, 2),
        "weak_signal_snr": cfg.weak_signal_snr,
        "weak_signal": cfg.weak_signal(prep.contact_snr),
        "film_limited_snr": cfg.film_limited_snr,
        "film_limited": cfg.film_limited(prep.contact_snr),
        "st_noise_n": None if prep.st_noise_n is None else round(prep.st_noise_n, 6),
        "noisy_st_noise_n": cfg.noisy_st_noise_n,
        "noisy_singletact": cfg.noisy_singletact(prep.st_noise_n),
        "gate_factor": pre.gate.factor,
        "objective": {
            "kernel_tau_ms": cfg.kernel_ms,
            "lambda_e": cfg.objective.lambda_e,
            "thres_1": cfg.objective.thres_1,
            "thres_2": cfg.objective.thres_2,
            "m_worst": cfg.objective.m_worst,
            "sine_weight": cfg.sine_weight,
            "count_weight": cfg.count_weight,
            "segmented_count_classes": list(cfg.segmented_count_classes),
            "refine": {c: cfg.refine[c] for c in cfg.refined()},
            "refine_sine_count_weights": {c: cfg.refine_sine_count_weights[c] for c in cfg.refined() if c in cfg.refine_sine_count_weights},
            "refine_count_margins": {c: cfg.refine_count_margins[c] for c in cfg.refined() if c in cfg.refine_count_margins},
            "vr_distance_classes": [c for c in cfg.refined() if c in cfg.vr_distance_classes],
            "input_stage_classes": list(cfg.input_stage_classes),
            "no_pvdf_classes": list(cfg.no_pvdf_classes),
            "excitatory_classes": list(cfg.excitatory_classes),
            "highpass_hz": {c: cfg.highpass_hz[c] for c in cfg.classes if c in cfg.highpass_hz},
            "max_refs_per_condition": cfg.max_refs_per_condition,
        },
        "optimizer": {"name": "CMA-ES (cma)", "popsize": cfg.popsize, "max_generations": cfg.max_generations, "restarts": {c: cfg.restarts_of(c) for c in fits},
                      "saturated_classes": [c for c in fits if cfg.saturated(c)]},
        "fit_seconds": round(seconds, 1),
        "fitted_classes": list(fits),
        "loss": {
            c: {
                "start": round(f.start_loss, 5),
                "train": {k: round(v, 5) for k, v in f.train.as_dict().items()} if f.train else {},
                "validation": {k: round(v, 5) for k, v in f.validation.as_dict().items()} if f.validation else {},
                "generations": f.generations,
                "evaluations": f.evaluations,
                "runs": [r.as_dict() for r in f.runs],
                "seconds": round(f.seconds, 1),
                **({"search": {"start": round(f.search.start_loss, 5), "best": round(f.search.best_loss, 5),
                               "generations": f.search.generations, "evaluations": f.search.evaluations,
                               "runs": [r.as_dict() for r in f.search.runs], "seconds": round(f.search.seconds, 1)}}
                   if f.search is not None else {}),
            }
            for c, f in fits.items()
        },
    }
    if init is not None and init.provenance.get("fitted_by") == "touchreal fit":
        prov["init"] = {k: init.provenance[k] for k in ("dataset", "fitted_classes", "class_window_ms", "window_ms") if k in init.provenance}
    params = EncoderParams(preprocess=pre, classes=classes, alignment=ReferenceAlignment(lag_ms=lag_ms, dataset=name), provenance=prov)
    return FitResult(params, fits, seconds, timings, len(first.trials), len(val_e))
