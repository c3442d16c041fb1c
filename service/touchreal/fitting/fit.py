"""Fit the encoder to a dataset's TouchSim reference spike trains (paper section 2.4).

Steps of :func:`fit_dataset`:

1. **Split** the ramp and sine trials by repeat (:func:`split_repeats`): within every condition the
   repeats are shuffled with the seed and the first half trains, the rest is held out. Validation
   never sees a training trial (nor its reference spikes). The split is recorded in the parameter
   file's provenance so ``touchreal evaluate`` can use exactly the held-out trials. With
   ``holdout=False`` every trial trains and nothing is held out (for a separate test recording).
2. **Calibrate** the PVDF stage (mains harmonics + spectral gate) on the contact-free baselines of
   the training trials (PVDF samples before ``onset_s``).
3. **Preprocess** every trial once per distinct causal PVDF window of the fitted classes (channels
   do not depend on the class parameters; each class is fitted on its own window's channels) and
   keep the 5 kHz channels in memory.
4. Per class, **CMA-ES** (``cma``) in the normalised space of :mod:`.space`, minimising the
   objective of :mod:`.objective` over all training trials; each generation is one LIF population
   per trial (:func:`encode_population`: the candidates are the neurons of one LIF population),
   split across worker processes (fork; the channel cache is inherited, not copied) or, through
   the same :class:`Executor` seam, across Dask workers (:mod:`.dask_executor`).
   The start is TouchSim's tau/ih, the class's weight direction and a small grid over the overall
   gain and the delay. For the classes of ``segmented_count_classes`` (default PC) the relative
   count loss of a ramp condition is taken per turning-point window (onset, hold, release, release
   end), so the fit cannot trade a missed spike at one turning point for an extra one at another.
5. Score the best candidate on the training and held-out trials; write everything into
   :class:`EncoderParams` with provenance.

Spike times enter the objective on the reference clock (stamp minus an alignment) and relative to
each trial's commanded onset (``onset_s``), so trials of one condition share a clock. The search
runs at an alignment of :data:`SEARCH_LAG_MS`, so a class may lead the reference by up to 250 ms
(the sensor's lag behind the commanded stimulus); the file records the smallest alignment that keeps
every class delay >= 0 (the class with the largest lead gets delay 0), kept classes of ``init``
re-expressed on it with the same reference-clock spikes. The fitter runs exactly the product encoder's code, so a fitted
parameter set behaves in the service as it did in the fit.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from ..analysis.turning_points import turning_points, window_edges
from ..encoding.encoder import encode_population, lowpass_channels
from ..params import ClassParams, EncoderParams, PreprocessParams, ReferenceAlignment, default_params
from ..preprocess.gate import calibrate
from ..preprocess.pipeline import preprocess_trial
from ..recording import Dataset, Trial
from ..settings import CLASSES, OUT_FS_HZ
from .objective import LossTerms, ObjectiveConfig, ReferenceSet, evaluate_loss
from .space import DELAY_RANGE_MS, DELAY_UNIT_MS, INITIAL_WEIGHTS, ParamSpace, touchsim_class_defaults

FIT_PROTOCOLS = ("ramp", "sine")
#: Alignment (ms) the search runs at: class delays of 0-500 ms then span reference-clock delays of
#: -250 ... +250 ms. The written file gets the smallest alignment that keeps every delay >= 0.
SEARCH_LAG_MS = 250.0
SPLIT_METHOD = "per-condition seeded shuffle of repeats (crc32(condition), seed); first half trains"
NO_SPLIT_METHOD = "none: every ramp/sine trial trains, nothing is held out"


# ------------------------------------------------------------------------------------- split


def _condition_rng(condition: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(condition.encode()), int(seed)])


def split_repeats(entries: Sequence[dict[str, Any]], seed: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(train, held-out) entries: per condition, shuffle the repeats with the seed; the first
    ``n // 2`` (at least 1) train, the rest are held out. A condition with one trial only trains."""
    by_cond: dict[str, list[dict[str, Any]]] = {}
    for e in entries:
        by_cond.setdefault(e["condition"], []).append(e)
    train, test = [], []
    for cond in sorted(by_cond):
        group = sorted(by_cond[cond], key=lambda e: (e["repeat"], e["id"]))
        order = _condition_rng(cond, seed).permutation(len(group))
        n_train = max(1, len(group) // 2)
        train += [group[i] for i in sorted(order[:n_train])]
        test += [group[i] for i in sorted(order[n_train:])]
    return train, test


# ------------------------------------------------------------------------------ configuration


def shipped_windows_ms() -> dict[str, float]:
    """Per class, the causal PVDF window (ms) it runs at in the shipped defaults (SA1 and RA on the
    16 ms fast path, PC on 128 ms): the windows a fit uses unless told otherwise."""
    p = default_params()
    return {c: p.window_ms(c) for c in CLASSES if c in p.classes}


@dataclass
class FitConfig:
    classes: tuple[str, ...] = CLASSES
    window_ms: float = 128.0  #: preprocessing window (ms): every class without its own entry in class_window_ms
    #: a class's own causal PVDF window (ms); default: the shipped windows (:func:`shipped_windows_ms`)
    class_window_ms: dict[str, float] = field(default_factory=shipped_windows_ms)
    holdout: bool = True  #: False: every trial trains (no held-out half)
    seed: int = 0
    kernel_ms: float = 10.0  #: kernel tau of the objective's D_kernel (eqs. 2-3)
    popsize: int = 12
    max_generations: int = 250  #: generations of the first CMA-ES run
    restarts: int = 1  #: IPOP restarts (population x2, generations /2 each)
    workers: int | None = None  #: None = all cores
    max_ramp_conditions: int | None = None  #: seeded subsample of ramp conditions (None = all)
    max_refs_per_condition: int = 80  #: reference trains kept per condition (whole repeats)
    sine_weight: float = 30.0  #: weight of a sine condition relative to a ramp condition (paper: 1)
    count_weight: float = 1.0  #: multiplier of L_rel in the objective (paper: 1)
    segmented_count_classes: tuple[str, ...] = ("PC",)  #: classes whose ramp count loss is taken per turning-point window (paper eq. 7: none)
    input_stage_classes: tuple[str, ...] = ("RA", "PC")  #: classes whose input stage (low-pass cutoff, negative lead) is fitted
    no_pvdf_classes: tuple[str, ...] = ()  #: classes fitted on the SingleTact channels alone (PVDF weights held at 0)
    progress: bool = True
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)

    def __post_init__(self) -> None:
        bad = [c for c in self.classes if c not in CLASSES]
        if bad or not self.classes:
            raise ValueError(f"classes must be a non-empty subset of {list(CLASSES)}, got {list(self.classes)}")
        bad = [c for c in self.input_stage_classes if c not in CLASSES]
        if bad:
            raise ValueError(f"input_stage_classes must be a subset of {list(CLASSES)}, got {list(self.input_stage_classes)}")
        bad = [c for c in self.class_window_ms if c not in CLASSES]
        if bad:
            raise ValueError(f"class_window_ms names unknown classes {bad}; expected a subset of {list(CLASSES)}")
        if not all(4.0 <= w <= 512.0 for w in (self.window_ms, *self.class_window_ms.values())):
            raise ValueError("window_ms must be in [4, 512]")
        if self.popsize < 4 or self.max_generations < 1:
            raise ValueError("popsize must be >= 4 and max_generations >= 1")
        if self.kernel_ms <= 0:
            raise ValueError("kernel_ms must be > 0")
        if not np.isfinite(self.count_weight) or self.count_weight < 0:
            raise ValueError("count_weight must be >= 0")
        bad = [c for c in self.no_pvdf_classes if c not in CLASSES]
        if bad:
            raise ValueError(f"no_pvdf_classes must be a subset of {list(CLASSES)}, got {list(self.no_pvdf_classes)}")
        bad = [c for c in self.segmented_count_classes if c not in CLASSES]
        if bad:
            raise ValueError(f"segmented_count_classes must be a subset of {list(CLASSES)}, got {list(self.segmented_count_classes)}")
        self.objective = ObjectiveConfig(
            **{**self.objective.__dict__, "kernel_tau_s": self.kernel_ms / 1000.0, "count_weight": float(self.count_weight)}
        )

    def window_of(self, cls: str) -> float:
        """Causal PVDF window (ms) class ``cls`` is fitted at."""
        return float(self.class_window_ms.get(cls, self.window_ms))


# ------------------------------------------------------------------------- cached trial data


@dataclass
class TrialData:
    """One preprocessed trial: ``channels`` (T, 4) start at grid index ``k0``; ``window_edges_s``:
    inner edges (s after the commanded onset) of a ramp's turning-point windows (empty otherwise)."""

    id: str
    condition: str
    protocol: str
    onset_s: float
    k0: int
    channels: np.ndarray
    reference: dict[str, list[np.ndarray]]  # class -> trains (onset-aligned), repeat-major
    ref_models: dict[str, int] = field(default_factory=dict)  # class -> models per repeat
    window_edges_s: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class TrialSet:
    trials: list[TrialData]
    conditions: list[str]  # condition names, index = condition id
    cond_index: np.ndarray  # (n_trials,) condition id of each trial

    def reference_set(self, cls: str, tau_s: float, max_refs: int, sine_weight: float = 1.0, segmented_count: bool = False) -> ReferenceSet:
        """Reference trains of ``cls`` per condition. At most ``max_refs`` per condition: every
        trial keeps its first r repeats (all models of each), r >= 1 chosen to fit the cap. With
        ``segmented_count`` a ramp condition's count loss is split at its trials' turning-point
        windows (the commanded turning points are the same for every repeat)."""
        members: list[list[TrialData]] = [[] for _ in self.conditions]
        for tr, c in zip(self.trials, self.cond_index):
            members[c].append(tr)
        groups: list[list[np.ndarray]] = []
        for c, trs in enumerate(members):
            trs = [t for t in trs if cls in t.reference]
            if not trs:
                raise ValueError(f"condition {self.conditions[c]} has no {cls} reference trains")
            n_models = trs[0].ref_models[cls]
            keep = max(1, max_refs // (len(trs) * n_models))
            groups.append([t for tr in trs for t in tr.reference[cls][: keep * tr.ref_models[cls]]])
        weights = [sine_weight if members[c][0].protocol == "sine" else 1.0 for c in range(len(self.conditions))]
        edges = [m[0].window_edges_s for m in members] if segmented_count else None
        return ReferenceSet.build(groups, tau_s, names=self.conditions, weights=weights, segment_edges=edges)


def _trial_data(entry: dict[str, Any], trial: Trial, pre: PreprocessParams, classes: Sequence[str]) -> TrialData:
    ch = preprocess_trial(trial, pre)
    onset = float(entry["onset_s"])
    ref: dict[str, list[np.ndarray]] = {}
    models: dict[str, int] = {}
    for cls in classes:
        if cls in trial.reference:
            r = trial.reference[cls]
            ref[cls] = [np.sort(np.asarray(t, np.float64)) - onset for t in r.trains()]
            models[cls] = r.n_models
    edges = window_edges([t for _, t, _ in turning_points(entry)]) if entry["protocol"] == "ramp" else np.zeros(0)
    return TrialData(entry["id"], entry["condition"], entry["protocol"], onset, int(ch.k0), np.ascontiguousarray(ch.data[:, 0, :]), ref, models, edges)


def build_trial_set(
    ds: Dataset, entries: Sequence[dict[str, Any]], pre: PreprocessParams, classes: Sequence[str], loaded: dict[str, Trial] | None = None
) -> TrialSet:
    """Preprocess the entries (``loaded`` may hold trials already read, by id)."""
    loaded = loaded or {}
    trials = [_trial_data(e, loaded[e["id"]] if e["id"] in loaded else ds.load(e), pre, classes) for e in entries]
    names = sorted({t.condition for t in trials})
    index = {n: i for i, n in enumerate(names)}
    return TrialSet(trials, names, np.array([index[t.condition] for t in trials], dtype=np.int64))


CONTACT_FREE_PROTOCOLS = ("ramp", "texture")  #: protocols whose pre-onset baseline has no contact


def baseline_segments(
    ds: Dataset, entries: Sequence[dict[str, Any]], margin_s: float = 0.02, loaded: dict[str, Trial] | None = None
) -> list[np.ndarray]:
    """Contact-free PVDF (V): samples before ``onset_s - margin_s`` of the ramp/texture entries
    (the sine probe rests on the skin; its vibration-free baselines are used only without ramps)."""
    loaded = loaded or {}
    free = [e for e in entries if e["protocol"] in CONTACT_FREE_PROTOCOLS] or list(entries)
    out = []
    for e in free:
        tr = loaded[e["id"]] if e["id"] in loaded else ds.load(e)
        seg = np.asarray(tr.pvdf[tr.pvdf_t < float(e["onset_s"]) - margin_s], np.float64)
        if seg.size:
            out.append(seg)
    return out


def channel_scale(trials: Sequence[TrialData], lowpass_hz: float | None = None) -> np.ndarray:
    """Typical magnitude of each channel: 99th percentile of |x| over the trials, after a class
    low-pass at ``lowpass_hz`` when given (it shrinks the fast channels, dPVDF most)."""
    allc = np.concatenate([lowpass_channels(t.channels, lowpass_hz) for t in trials], axis=0)
    sc = np.percentile(np.abs(allc), 99.0, axis=0)
    return np.where(sc > 0, sc, 1.0)


def estimate_lag_s(trials: Sequence[TrialData]) -> float:
    """Median delay between the commanded onset and the SingleTact rise (10 % of its range) over
    ramp trials (0 without ramps): the rig's lag behind its reference, recorded as the parameter
    file's ``alignment`` (the SingleTact channel does not depend on the PVDF window)."""
    lags = []
    for t in trials:
        if t.protocol != "ramp":
            continue
        st = t.channels[:, 0]
        base = np.median(st[: max(1, min(st.size, 50))])
        rng = st.max() - base
        if rng <= 0:
            continue
        k = int(np.argmax(st > base + 0.1 * rng))
        lags.append((t.k0 + k) / OUT_FS_HZ - t.onset_s)
    return float(np.median(lags)) if lags else 0.0


# --------------------------------------------------------------------------- fast simulation


def simulate(trials: Sequence[TrialData], params: Sequence[ClassParams], lag_s: float = 0.0) -> list[list[np.ndarray]]:
    """Onset-aligned spike trains ``[parameter set][trial]`` on the reference clock (stamps minus
    the rig's lag ``lag_s``): every set is one neuron of the product encoder's population
    (:func:`~touchreal.encoding.encoder.encode_population`)."""
    out: list[list[np.ndarray]] = [[] for _ in params]
    for tr in trials:
        for j, train in enumerate(encode_population(tr.channels, tr.k0 / OUT_FS_HZ, params)):
            out[j].append(train - lag_s - tr.onset_s)
    return out


# ------------------------------------------------------------------------- parallel evaluation
# The seam between the optimiser and where its candidates are evaluated: an :class:`Executor`
# maps (class, candidate batch) to losses from a :class:`FitState`. :class:`LocalExecutor` uses
# forked processes on this machine; ``touchreal.fitting.dask_executor`` uses Dask workers, each of
# which rebuilds the same state once from the :class:`FitSource` (see :func:`prepare`).


@dataclass(frozen=True)
class FitSource:
    """Everything a fit's training state is built from (a worker rebuilds it from this alone):
    the dataset folder (as seen by the worker), the configuration and the ``--init`` file."""

    dataset_dir: str
    cfg: FitConfig
    init: EncoderParams | None = None


@dataclass
class FitState:
    """What evaluating a candidate needs: per class its search space, references and preprocessed
    training trials; the objective; the search's alignment ``lag_s`` (s; spikes compared at stamp minus it)."""

    spaces: dict[str, ParamSpace]
    refs: dict[str, ReferenceSet]
    train: dict[str, TrialSet]
    objective: ObjectiveConfig
    lag_s: float


Losses = list[tuple[float, dict[str, float]]]  #: per candidate: (total loss, loss terms)


def losses(state: FitState, cls: str, xs: np.ndarray) -> Losses:
    """Objective of every candidate ``xs`` (n, dim) of class ``cls`` (a non-finite loss counts as 1e6).
    Each candidate's loss depends on that candidate alone, so any split of a batch gives the same numbers."""
    space, tset = state.spaces[cls], state.train[cls]
    trains = simulate(tset.trials, [space.decode(x) for x in xs], state.lag_s)
    out = []
    for tr in trains:
        terms = evaluate_loss(tr, tset.cond_index, state.refs[cls], state.objective)
        total = terms.total if np.isfinite(terms.total) else 1e6
        out.append((float(total), terms.as_dict()))
    return out


class Executor(Protocol):
    """Evaluates a batch of candidates of one class: ``executor(cls, xs) -> losses``, in order."""

    def __call__(self, cls: str, xs: np.ndarray) -> Losses: ...

    def close(self) -> None: ...


ExecutorFactory = Callable[[FitSource, FitState], Executor]

_STATE: dict[str, FitState] = {}  # the local worker processes' state (inherited by fork)


def _local_losses(cls: str, xs: np.ndarray) -> Losses:
    return losses(_STATE["state"], cls, xs)


def _init_worker(state: FitState | None) -> None:
    if state is not None:
        _STATE["state"] = state


class LocalExecutor:
    """Evaluates candidate batches in-process or split across ``workers`` forked processes (the
    state is inherited, not copied; numba kernels are compiled before forking)."""

    def __init__(self, state: FitState, workers: int):
        _STATE["state"] = state
        warm_up()
        self.state = state
        self.workers = workers
        self.pool: ProcessPoolExecutor | None = None
        if workers > 1:
            methods = mp.get_all_start_methods()
            if "fork" in methods:
                self.pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"), initializer=_init_worker, initargs=(None,))
            else:  # pragma: no cover - platforms without fork: ship the cache once per worker
                self.pool = ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(state,))

    @classmethod
    def factory(cls, workers: int | None) -> ExecutorFactory:
        """Executor factory for :func:`fit_dataset`: ``workers`` processes (None = all cores, at most the population)."""
        return lambda source, state: cls(state, max(1, min(workers or os.cpu_count() or 1, source.cfg.popsize)))

    def __call__(self, cls: str, xs: np.ndarray) -> Losses:
        xs = np.asarray(xs, np.float64)
        if self.pool is None or len(xs) < 2:
            return losses(self.state, cls, xs)
        chunks = [c for c in np.array_split(xs, self.workers) if len(c)]
        res = []
        for part in self.pool.map(_local_losses, [cls] * len(chunks), chunks):
            res += part
        return res

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None
        _STATE.pop("state", None)


def warm_up() -> None:
    """Compile the numba kernels (before forking, so workers inherit them; once per Dask worker)."""
    encode_population(np.zeros((16, 4)), 0.0, [ClassParams(weights=[0.0] * 8, i_sat=0, tau_ms=1, ih=[0, 0], delay_ms=0)])
    refs = ReferenceSet.build([[np.array([0.1])]], 0.01)
    evaluate_loss([np.array([0.1])], [0], refs, ObjectiveConfig())


# ---------------------------------------------------------------------------------- the fit


@dataclass
class ClassFit:
    cls: str
    params: ClassParams
    x: np.ndarray
    generations: int
    evaluations: int
    seconds: float
    history: list[float]  # best-so-far loss per generation
    start_loss: float
    train: LossTerms | None = None
    validation: LossTerms | None = None


@dataclass
class FitResult:
    params: EncoderParams
    classes: dict[str, ClassFit]
    seconds: float
    timings: dict[str, float]
    n_train: int
    n_validation: int


def _cma_seed(seed: int, cls: str, run: int = 0) -> int:
    return int(np.random.SeedSequence([int(seed), CLASSES.index(cls), run]).generate_state(1)[0] % (2**31 - 2)) + 1


def _cma(space: ParamSpace, x0: np.ndarray, popsize: int, generations: int, seed: int):
    import cma

    lo, hi = space.bounds()
    opts = {
        "seed": seed,
        "popsize": popsize,
        "bounds": [list(lo), list(hi)],
        "CMA_stds": list(space.stds()),
        "maxiter": generations,
        "verbose": -9,
        "tolfun": 1e-6,
        "tolflatfitness": 10,
    }
    if space.fixed():
        opts["fixed_variables"] = space.fixed()
    return cma.CMAEvolutionStrategy(list(x0), 1.0, opts)


GRID_GAINS = 2.0 ** np.arange(-4, 5)  #: overall weight gains of the start grid
GRID_LOG_TAU = (-1.4, 0.0, 1.4)  #: tau multipliers exp(.) of the start grid (x0.25, x1, x4)
GRID_DELAYS_MS = (-20.0, 0.0, 20.0)  #: delay offsets of the start grid (clipped to delays >= 0)


def start_grid(space: ParamSpace, starts: Sequence[np.ndarray], delay0_ms: float) -> np.ndarray:
    """Every start x gain x tau multiplier x delay offset (deterministic)."""
    out = []
    for x in starts:
        for g in GRID_GAINS:
            for lt in GRID_LOG_TAU:
                for dd in GRID_DELAYS_MS:
                    y = space.with_gain(x, g)
                    y[8] = x[8] + lt
                    y[11] = (delay0_ms + dd) / DELAY_UNIT_MS
                    out.append(space.clip(y))
    return np.array(out)


def fit_class(
    cls: str,
    space: ParamSpace,
    evaluate: Executor,
    cfg: FitConfig,
    starts: Sequence[np.ndarray],
    delay0_ms: float,
) -> ClassFit:
    """CMA-ES for one class from the best point of :func:`start_grid` around ``starts``, then
    ``cfg.restarts`` IPOP restarts from the same point with their own seeds (population doubled,
    generations halved each time, so every run costs about the same); the best point ever
    evaluated wins. Independent restarts matter: on rig-v1, runs that differ only in their seed
    end in optima that differ by up to 0.2 in loss, while restarting from a converged point does
    not move it."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    grid = start_grid(space, starts, delay0_ms)
    losses = [r[0] for r in evaluate(cls, grid)]
    n_evals = len(grid)
    best = int(np.argmin(losses))
    x0 = grid[best]
    start_loss = float(losses[best])
    best_x, best_f = x0.copy(), start_loss
    history: list[float] = []
    runs = [(cfg.popsize, cfg.max_generations)]
    for k in range(1, cfg.restarts + 1):  # IPOP-style: double the population, halve the generations
        runs.append((cfg.popsize * 2**k, max(1, cfg.max_generations // 2**k)))
    bar = tqdm(total=sum(g for _, g in runs), desc=f"fit {cls}", unit="gen", disable=not cfg.progress, dynamic_ncols=True)
    try:
        for k, (popsize, gens) in enumerate(runs):
            es = _cma(space, x0, popsize, gens, _cma_seed(cfg.seed, cls, k))
            done = 0
            while not es.stop():
                xs = np.asarray(es.ask())
                res = evaluate(cls, xs)
                f = [r[0] for r in res]
                es.tell(list(xs), f)
                n_evals += len(xs)
                done += 1
                i = int(np.argmin(f))
                if f[i] < best_f:
                    best_f, best_x = float(f[i]), xs[i].copy()
                history.append(best_f)
                bar.update(1)
                bar.set_postfix(run=k, loss=f"{best_f:.4f}", gen_median=f"{float(np.median(f)):.4f}")
            bar.update(gens - done)  # early stop of a run
    finally:
        bar.close()
    return ClassFit(
        cls=cls,
        params=space.decode(best_x),
        x=space.clip(best_x),
        generations=len(history),
        evaluations=n_evals,
        seconds=time.perf_counter() - t_start,
        history=history,
        start_loss=start_loss,
    )


@dataclass
class Prepared:
    """A fit's data before optimisation (:func:`prepare`): the opened dataset, its split, the
    calibrated preprocessing, the evaluation state, the measured rig lag and the step timings."""

    ds: Dataset
    train_e: list[dict[str, Any]]
    val_e: list[dict[str, Any]]
    pre: PreprocessParams
    n_baselines: int
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
    pre = calibrate(segments, base.model_copy(update={"window_ms": float(cfg.window_ms)}))
    timings["calibrate_s"] = time.perf_counter() - t
    log(f"PVDF calibration on {len(segments)} contact-free baselines: notch harmonics {pre.notch_harmonics}, "
        f"gate on {len(pre.gate.freqs_hz) if pre.gate else 0} bins")

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

    tau_s = cfg.objective.kernel_tau_s
    spaces = {}
    for c in cfg.classes:  # an input-stage class's weights are normalised behind its start cutoff
        lp0 = touchsim_class_defaults()[c]["lowpass_hz"] if c in cfg.input_stage_classes else None
        spaces[c] = ParamSpace.for_class(c, channel_scale(train[c].trials, lp0), lp0 is not None, c not in cfg.no_pvdf_classes)
    refs = {c: train[c].reference_set(c, tau_s, cfg.max_refs_per_condition, cfg.sine_weight, c in cfg.segmented_count_classes) for c in cfg.classes}
    state = FitState(spaces=spaces, refs=refs, train=train, objective=cfg.objective, lag_s=lag_s)
    return Prepared(ds, train_e, val_e, pre, len(segments), state, rig_lag_ms, timings)


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
    ds, val_e, pre, timings, rig_lag_ms = prep.ds, prep.val_e, prep.pre, prep.timings, prep.rig_lag_ms
    name = str(ds.manifest.get("name", ""))
    spaces, refs, train, lag_s, tau_s = prep.state.spaces, prep.state.refs, prep.state.train, prep.state.lag_s, cfg.objective.kernel_tau_s
    first = train[min(cfg.classes, key=cfg.window_of)]  # the smallest window's trial set (counts are the same in all)
    t = time.perf_counter()
    evaluator = (executor or LocalExecutor.factory(cfg.workers))(source, prep.state)
    timings["executor_start_s"] = time.perf_counter() - t  # Dask: every worker has loaded and preprocessed the dataset
    fits: dict[str, ClassFit] = {}
    try:
        for cls in cfg.classes:
            sp = spaces[cls]
            d0 = SEARCH_LAG_MS - rig_lag_ms  # spikes start aligned with the SingleTact's rise
            if init is not None and cls in init.classes:
                start = init.classes[cls]
                d0 = start.delay_ms - init.alignment.lag_ms + SEARCH_LAG_MS  # the same reference-clock spikes
                starts = [sp.clip(sp.encode(start.model_copy(update={"delay_ms": d0})))]
            else:
                starts = [sp.initial(d0, v) for v in range(len(INITIAL_WEIGHTS[cls]))]
            fits[cls] = fit_class(cls, sp, evaluator, cfg, starts, d0)
    finally:
        evaluator.close()

    t = time.perf_counter()
    val: dict[float, TrialSet] = {}
    for cls, f in fits.items():
        f.params = f.params.model_copy(update={"window_ms": None if cfg.window_of(cls) == pre.window_ms else cfg.window_of(cls)})
        f.train = evaluate_loss(simulate(train[cls].trials, [f.params], lag_s)[0], train[cls].cond_index, refs[cls], cfg.objective)
        if val_e:
            w = cfg.window_of(cls)
            if w not in val:
                val[w] = build_trial_set(ds, val_e, pre.model_copy(update={"window_ms": w}), cfg.classes)
            vref = val[w].reference_set(cls, tau_s, cfg.max_refs_per_condition, cfg.sine_weight, cls in cfg.segmented_count_classes)
            f.validation = evaluate_loss(simulate(val[w].trials, [f.params], lag_s)[0], val[w].cond_index, vref, cfg.objective)
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
        "objective": {
            "kernel_tau_ms": cfg.kernel_ms,
            "lambda_e": cfg.objective.lambda_e,
            "thres_1": cfg.objective.thres_1,
            "thres_2": cfg.objective.thres_2,
            "m_worst": cfg.objective.m_worst,
            "sine_weight": cfg.sine_weight,
            "count_weight": cfg.count_weight,
            "segmented_count_classes": list(cfg.segmented_count_classes),
            "input_stage_classes": list(cfg.input_stage_classes),
            "no_pvdf_classes": list(cfg.no_pvdf_classes),
            "max_refs_per_condition": cfg.max_refs_per_condition,
        },
        "optimizer": {"name": "CMA-ES (cma)", "popsize": cfg.popsize, "max_generations": cfg.max_generations, "restarts": cfg.restarts},
        "fit_seconds": round(seconds, 1),
        "fitted_classes": list(fits),
        "loss": {
            c: {
                "start": round(f.start_loss, 5),
                "train": {k: round(v, 5) for k, v in f.train.as_dict().items()} if f.train else {},
                "validation": {k: round(v, 5) for k, v in f.validation.as_dict().items()} if f.validation else {},
                "generations": f.generations,
                "evaluations": f.evaluations,
                "seconds": round(f.seconds, 1),
            }
            for c, f in fits.items()
        },
    }
    if init is not None and init.provenance.get("fitted_by") == "touchreal fit":
        prov["init"] = {k: init.provenance[k] for k in ("dataset", "fitted_classes", "class_window_ms", "window_ms") if k in init.provenance}
    params = EncoderParams(preprocess=pre, classes=classes, alignment=ReferenceAlignment(lag_ms=lag_ms, dataset=name), provenance=prov)
    return FitResult(params, fits, seconds, timings, len(first.trials), len(val_e))


def fitted_on_every_trial(params: EncoderParams, ds: Dataset) -> bool:
    """True if ``params`` were fitted on this dataset by ``touchreal fit`` without a held-out part."""
    prov = params.provenance
    return (prov.get("fitted_by") == "touchreal fit" and prov.get("split_method") == NO_SPLIT_METHOD
            and str(prov.get("dataset", "")) == str(ds.manifest.get("name", "")))


def params_split_seed(params: EncoderParams, ds: Dataset) -> int | None:
    """The split seed if ``params`` were fitted on this dataset by ``touchreal fit`` with a held-out
    half, else None."""
    prov = params.provenance
    if prov.get("fitted_by") != "touchreal fit" or prov.get("split_method") != SPLIT_METHOD:
        return None
    if str(prov.get("dataset", "")) != str(ds.manifest.get("name", "")):
        return None
    seed = prov.get("split_seed")
    return int(seed) if isinstance(seed, (int, float)) else None
