"""Fit the encoder to a dataset's TouchSim reference spike trains (paper section 2.4).

Steps of :func:`fit_dataset`:

1. **Split** the ramp and sine trials by repeat (:mod:`touchreal.splits`): within every condition
   the repeats are shuffled with the seed and the first half trains, the rest is held out.
   Validation never sees a training trial (nor its reference spikes). The split is recorded in the
   parameter file's provenance so ``touchreal evaluate`` can use exactly the held-out trials. With
   ``holdout=False`` every trial trains and nothing is held out (for a separate test recording).
2. **Calibrate** the PVDF stage (mains harmonics + spectral gate) on the contact-free baselines of
   the training trials (PVDF samples before ``onset_s``), measure the build's profile
   (:mod:`.profile`: contact SNR, SingleTact noise) and resolve the fit's plan for it
   (:mod:`.policy`: the defaults, the rules the profile meets, the recipe); :func:`measure`.
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
from ..recording import Dataset, Trial
from ..splits import FIT_PROTOCOLS, split_repeats
from .calibration import calibrate_pvdf
from .config import FitConfig
from .describe import log_line
from .executor import ExecutorFactory, FitSource, FitState, LocalExecutor
from .objective import ReferenceSet, evaluate_loss
from .plan import FitPlan, parse_stage_key, stage_key
from .policy import Resolution, measured_with, resolve
from .profile import measure_profile
from .provenance import provenance
from .search import ClassFit, Searcher
from .space import INITIAL_WEIGHTS, ParamSpace, touchsim_class_defaults
from .trials import TrialSet, baseline_segments, build_trial_set, channel_scale, estimate_lag_s, simulate

#: Alignment (ms) the search runs at: class delays of 0-500 ms then span reference-clock delays of
#: -250 ... +250 ms. The written file gets the smallest alignment that keeps every delay >= 0.
SEARCH_LAG_MS = 250.0


@dataclass
class FitResult:
    """A fit's parameter file, each class's search (and refinement), the wall time (s) in all and per
    step, the trials it trained and was scored on, and the plan it ran."""

    params: EncoderParams
    classes: dict[str, ClassFit]
    seconds: float
    timings: dict[str, float]
    n_train: int
    n_validation: int
    resolution: Resolution  #: the plan the fit ran, with the profile and rules it was resolved from


@dataclass
class Measured:
    """A dataset's training half, its calibrated PVDF stage and its profile (steps 1-2 of the fit),
    with the plan resolved for it."""

    ds: Dataset
    train_e: list[dict[str, Any]]
    val_e: list[dict[str, Any]]
    loaded: dict[str, Trial]  #: the training trials, by id
    pre: PreprocessParams  #: calibrated, with the plan's gate factor
    n_baselines: int
    resolution: Resolution


@dataclass
class Prepared:
    """A fit's data before optimisation (:func:`prepare`): the measured dataset, the evaluation
    state, the measured rig lag and the step timings."""

    measured: Measured
    state: FitState
    rig_lag_ms: float  #: the SingleTact's rise after the commanded onset (the search runs at SEARCH_LAG_MS)
    timings: dict[str, float]

    @property
    def plan(self) -> FitPlan:
        """The plan the fit runs."""
        return self.measured.resolution.plan


def measure(source: FitSource, log: Callable[[str], None] | None = None) -> Measured:
    """Split the dataset, calibrate the PVDF stage on the training baselines, measure the build's
    profile and resolve the fit's plan for it (steps 1-2; deterministic)."""
    cfg, init, dataset_dir = source.cfg, source.init, source.dataset_dir
    log = log or (lambda s: None)
    data = measured_with(cfg.classes, cfg.recipe)  # the window and trials the profile is measured with
    ds = Dataset.open(dataset_dir)
    entries = [e for e in ds.entries() if e["protocol"] in FIT_PROTOCOLS and e.get("reference")]
    if not entries:
        raise ValueError(f"{dataset_dir}: no ramp or sine trials with reference spike trains")
    train_e, val_e = split_repeats(entries, cfg.seed) if cfg.holdout else (list(entries), [])
    if data.max_ramp_conditions is not None:
        conds = sorted({e["condition"] for e in train_e if e["protocol"] == "ramp"})
        if len(conds) > data.max_ramp_conditions:
            keep = set(np.random.default_rng(cfg.seed).choice(conds, data.max_ramp_conditions, replace=False).tolist())
            train_e = [e for e in train_e if e["protocol"] != "ramp" or e["condition"] in keep]
    log(f"split: {len(train_e)} training / {len(val_e)} held-out trials" + (f" (seed {cfg.seed})" if cfg.holdout else " (no held-out part)"))
    loaded = {e["id"]: ds.load(e) for e in train_e}
    base = init.preprocess if init is not None else PreprocessParams()
    segments = baseline_segments(ds, train_e, loaded=loaded)
    pre = calibrate_pvdf(segments, base.model_copy(update={"window_ms": float(data.window_ms)}))
    res = resolve(measure_profile(ds, train_e, loaded, pre), cfg.classes, cfg.recipe)
    pre = pre.model_copy(update={"gate": pre.gate.model_copy(update={"factor": res.plan.gate_factor})})
    log(f"PVDF calibration on {len(segments)} contact-free baselines: mains {pre.mains_hz:g} Hz, notch harmonics {pre.notch_harmonics}, "
        f"gate on {len(pre.gate.freqs_hz)} bins at {pre.gate.factor:g} x the noise")
    log(log_line(res))
    return Measured(ds, train_e, val_e, loaded, pre, len(segments), res)


def prepare(source: FitSource, log: Callable[[str], None] | None = None) -> Prepared:
    """Measure and resolve (:func:`measure`), preprocess and align (steps 1-3 of the fit);
    deterministic, so every Dask worker that runs it on the same source holds the same state as the driver."""
    log = log or (lambda s: None)
    t = time.perf_counter()
    m = measure(source, log)
    timings = {"calibrate_s": time.perf_counter() - t}
    plan, ds, pre = m.resolution.plan, m.ds, m.pre

    t = time.perf_counter()
    windows = sorted({plan.window_of(c) for c in plan.classes})
    trainsets: dict[float, TrialSet] = {}
    for w in windows:  # one preprocessing per distinct window
        trainsets[w] = build_trial_set(ds, m.train_e, pre.model_copy(update={"window_ms": w}), list(plan.classes), m.loaded)
    m.loaded.clear()
    train = {c: trainsets[plan.window_of(c)] for c in plan.classes}
    timings["preprocess_s"] = time.perf_counter() - t
    first = trainsets[windows[0]]
    rig_lag_ms = round(1000.0 * estimate_lag_s(first.trials), 3)
    lag_s = SEARCH_LAG_MS / 1000.0  # the search's alignment; the file gets the smallest that keeps every delay >= 0
    log(f"preprocessed at {windows} ms in {timings['preprocess_s']:.1f} s; channel scale "
        f"{np.round(channel_scale(first.trials), 4).tolist()}; rig lag {rig_lag_ms:.1f} ms (SingleTact rise after the commanded onset)")

    spaces = {}
    for c, cp in plan.classes.items():  # an input-stage class's weights are normalised behind its start cutoff
        lp0 = touchsim_class_defaults()[c]["lowpass_hz"] if cp.input_stage else None
        spaces[c] = ParamSpace.for_class(c, channel_scale(train[c].trials, lp0), input_stage=cp.input_stage, pvdf=cp.pvdf,
                                         excitatory=cp.excitatory, highpass_hz=cp.highpass_hz)
    for c in plan.refined():  # a refinement evaluates on its class's trials and space
        spaces[stage_key(c, True)], train[stage_key(c, True)] = spaces[c], train[c]
    refs = {key: references(train[key], key, plan) for key in train}
    state = FitState(plan=plan, spaces=spaces, refs=refs, train=train, lag_s=lag_s)
    return Prepared(m, state, rig_lag_ms, timings)


def references(tset: TrialSet, key: str, plan: FitPlan) -> ReferenceSet:
    """The reference set of a class's search (``key`` = the class: counted per turning point if its
    plan says so) or of its refinement (whole-trial counts; its distance and sine count weight)."""
    cls, refinement = parse_stage_key(key)
    cp = plan.classes[cls]
    refine = cp.refine if refinement else None
    return tset.reference_set(cls, plan.kernel_ms / 1000.0, plan.max_refs_per_condition, plan.sine_weight,
                              segmented_count=not refinement and cp.segmented_count,
                              vr_normalised=refine is not None and refine.vr_distance,
                              sine_count_weight=refine.sine_count_weight if refine is not None else None)


def fit_dataset(
    dataset_dir: str | os.PathLike,
    cfg: FitConfig | None = None,
    init: EncoderParams | None = None,
    log: Callable[[str], None] | None = None,
    executor: ExecutorFactory | None = None,
) -> FitResult:
    """Fit every class of ``cfg.classes`` on the dataset's ramp + sine training trials, as the plan
    resolved for the build says (each class at its own causal PVDF window). ``executor`` makes the
    candidate evaluator (default :meth:`LocalExecutor.factory` with ``cfg.workers``; Dask:
    ``touchreal.fitting.dask_executor``)."""
    cfg = cfg or FitConfig()
    log = log or (lambda s: None)
    t_all = time.perf_counter()
    source = FitSource(str(dataset_dir), cfg, init)
    prep = prepare(source, log)
    plan, m = prep.plan, prep.measured
    pre, timings, rig_lag_ms = m.pre, prep.timings, prep.rig_lag_ms
    spaces, refs, train, lag_s = prep.state.spaces, prep.state.refs, prep.state.train, prep.state.lag_s
    first = train[min(plan.classes, key=plan.window_of)]  # the smallest window's trial set (counts are the same in all)
    t = time.perf_counter()
    evaluator = (executor or LocalExecutor.factory(cfg.workers))(source, prep.state)
    timings["executor_start_s"] = time.perf_counter() - t  # Dask: every worker has loaded and preprocessed the dataset
    jobs = {}
    for position, cls in enumerate(plan.classes):
        sp = spaces[cls]
        d0 = SEARCH_LAG_MS - rig_lag_ms  # spikes start aligned with the SingleTact's rise
        if init is not None and cls in init.classes:
            start = init.classes[cls]
            d0 = start.delay_ms - init.alignment.lag_ms + SEARCH_LAG_MS  # the same reference-clock spikes
            starts = [sp.clip(sp.encode(start.model_copy(update={"delay_ms": d0})))]
        else:
            starts = [sp.initial(d0, v) for v in range(len(INITIAL_WEIGHTS[cls]))]
        jobs[cls] = (Searcher(sp, evaluator, cfg.seed, cfg.progress, position), starts, d0)
    try:  # every class searches at once, so the workers never wait for one class's next generation
        with ThreadPoolExecutor(len(jobs), thread_name_prefix="fit") as pool:
            futures = {cls: pool.submit(searcher.search_and_refine, cls, plan, starts, d0)
                       for cls, (searcher, starts, d0) in jobs.items()}
            fits: dict[str, ClassFit] = {cls: f.result() for cls, f in futures.items()}
    finally:
        evaluator.close()

    t = time.perf_counter()
    val: dict[float, TrialSet] = {}
    for cls, f in fits.items():  # scored on the objective of the class's last stage
        key, w = stage_key(cls, f.search is not None), plan.window_of(cls)
        f.params = f.params.model_copy(update={"window_ms": None if w == pre.window_ms else w})
        f.train = evaluate_loss(simulate(train[cls].trials, [f.params], lag_s)[0], train[cls].cond_index, refs[key], plan.objective_of(key))
        if m.val_e:
            if w not in val:
                val[w] = build_trial_set(m.ds, m.val_e, pre.model_copy(update={"window_ms": w}), list(plan.classes))
            f.validation = evaluate_loss(simulate(val[w].trials, [f.params], lag_s)[0], val[w].cond_index, references(val[w], key, plan),
                                         plan.objective_of(key))
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
    name = str(m.ds.manifest.get("name", ""))
    prov = provenance(m.ds, cfg, m.resolution, fits, init=init, n_train=len(first.trials), n_validation=len(m.val_e),
                      n_baselines=m.n_baselines, rig_lag_ms=rig_lag_ms, seconds=seconds)
    params = EncoderParams(preprocess=pre, classes=classes, alignment=ReferenceAlignment(lag_ms=lag_ms, dataset=name), provenance=prov)
    return FitResult(params, fits, seconds, timings, len(first.trials), len(m.val_e), m.resolution)
