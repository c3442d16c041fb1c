"""``touchreal fit DATASET_DIR --out PARAMS.json``: fit the encoder to a dataset's TouchSim references."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..settings import CLASSES, DEFAULT_WINDOW_MS

if TYPE_CHECKING:
    from ..params import EncoderParams
    from .config import FitConfig
    from .executor import ExecutorFactory
    from .fit import FitResult


def register(sub: argparse._SubParsersAction) -> None:
    from .config import (DEFAULT_GATE_FACTOR, DEFAULT_REFINE, FILM_LIMITED_COUNT_MARGINS, FILM_LIMITED_HIGHPASS_HZ,
                         FILM_LIMITED_SINE_COUNT_WEIGHTS, NOISY_ST_RESTARTS, WEAK_SIGNAL_GATE_FACTOR, WEAK_SIGNAL_SINE_COUNT_WEIGHTS,
                         FitConfig)

    p = sub.add_parser(
        "fit",
        help="fit SA1/RA/PC encoder parameters to a dataset's TouchSim reference spike trains",
        description="Per afferent class, CMA-ES on the paper's objective (eqs. 1-10) over the ramp and sine "
        "training trials (split by repeat; the rest is held out for `touchreal evaluate`). Calibrates the PVDF "
        "gate on the contact-free baselines. See docs/fitting.md.",
    )
    p.add_argument("datasets", type=Path, nargs="+", metavar="DATASET_DIR",
                   help="dataset folder (manifest.json + trials/); several (one per sensor) are fitted one after another, "
                   "or side by side on one Dask cluster")
    p.add_argument("--out", type=Path, required=True, metavar="PARAMS.json",
                   help="parameter file to write; with several datasets a folder, receiving DATASET_DIR-name.json each")
    p.add_argument("--classes", default=",".join(CLASSES), help="comma-separated classes to fit (default: all)")
    p.add_argument("--window-ms", type=parse_windows, default=None, metavar="W|CLS=W,...",
                   help="causal PVDF window (ms) of every class, e.g. 128, or per class, e.g. SA1=16,RA=16,PC=128 "
                   "(classes not named take a bare number given in the list, else 128); default: the windows of the "
                   "shipped parameters (SA1=16,RA=16,PC=128, the fast path)")
    p.add_argument("--no-pvdf-classes", default="", metavar="CLS,...",
                   help="classes fitted on the SingleTact channels alone (PVDF and dPVDF weights held at 0)")
    p.add_argument("--excitatory-classes", default=None, metavar="CLS,...|none",
                   help="classes whose film weights (w5, w6: both polarities of PVDF) are held >= 0, so pressing and "
                   "releasing both excite them, as in every TouchSim RA model; 'none' for the paper's unconstrained "
                   "weights (default: RA)")
    p.add_argument("--highpass", type=parse_highpass, default=None, metavar="CLS=HZ,...|none",
                   help="classes whose input gets a 1st-order high-pass at this cutoff (Hz), held fixed: it removes the "
                   f"PVDF amplifier's slow baseline wander; 'none' for no high-pass (default: {_weights_text(FILM_LIMITED_HIGHPASS_HZ)} "
                   "on a film-limited build, else none)")
    p.add_argument("--no-holdout", action="store_true",
                   help="train on every ramp/sine trial (no held-out half; evaluate on a separate recording)")
    p.add_argument("--seed", type=int, default=0, help="seed of the train/held-out split and of CMA-ES (default 0)")
    p.add_argument("--generations", type=int, default=None, help="CMA-ES generations of the first run per class (default 250)")
    p.add_argument("--popsize", type=int, default=None, help="CMA-ES population size (default 12)")
    p.add_argument("--restarts", type=parse_restarts, default=None, metavar="N|CLS=N,...",
                   help="independent IPOP restarts beside a class's first run (same start, own seed, population x2, "
                   "generations /2): N for every class, or per class (a bare N in the list sets the classes not named, "
                   f"else they have none) (default: {_weights_text(NOISY_ST_RESTARTS)} on a build whose SingleTact noise "
                   "is above --noisy-st-noise, else none)")
    p.add_argument("--kernel-ms", type=float, default=None, help="kernel time constant of the objective (default 10 ms)")
    p.add_argument("--sine-weight", type=float, default=None, help="weight of one sine condition relative to one ramp condition")
    p.add_argument("--count-weight", type=float, default=None,
                   help="multiplier of the relative spike-count loss L_rel in the search's objective (default 1 = the paper's eq. 1)")
    p.add_argument("--segmented-count-classes", default=None,
                   help="comma-separated classes whose ramp count loss is taken per turning-point window, or 'none' for "
                   "the paper's whole-trial count, in the search (default: PC)")
    p.add_argument("--refine", type=parse_class_weights, default=None, metavar="CLS=K,...|none",
                   help="classes refined after their search by a second CMA-ES run from its best point, each with the count "
                   f"weight K of the refinement's objective (whole-trial counts), or 'none' for the paper's single search "
                   f"(default {_weights_text(DEFAULT_REFINE)})")
    p.add_argument("--refine-sine-count-weights", type=parse_class_weights, default=None, metavar="CLS=W,...|none",
                   help="refined classes whose refinement's count term weighs one sine condition W (1: the plain mean over "
                   "conditions the held-out report reads), or 'none'; the others, and every distance, keep --sine-weight "
                   f"(default: none, {_weights_text(WEAK_SIGNAL_SINE_COUNT_WEIGHTS)} on a weak-signal build, "
                   f"{_weights_text(FILM_LIMITED_SINE_COUNT_WEIGHTS)} on a film-limited one)")
    p.add_argument("--refine-count-margins", type=parse_class_weights, default=None, metavar="CLS=M,...|none",
                   help="refined classes whose refinement does not charge a relative count error up to M (e.g. 0.2): "
                   f"within it the distance alone decides; 'none' (default: {_weights_text(FILM_LIMITED_COUNT_MARGINS)} on a "
                   "film-limited build, else none)")
    p.add_argument("--gate-factor", type=float, default=None, help="the PVDF spectral gate keeps bins above this multiple of "
                   f"the noise calibrated on the baselines (default: {DEFAULT_GATE_FACTOR:g}, or {WEAK_SIGNAL_GATE_FACTOR:g} on a "
                   "weak-signal build)")
    p.add_argument("--weak-signal-snr", type=float, default=None, help="a build whose PVDF contact SNR (99th percentile of "
                   "|PVDF| after the contact onsets of the training ramps over the baseline noise RMS) is below this is a "
                   f"weak-signal build; 0: none is (default {FitConfig.weak_signal_snr:g})")
    p.add_argument("--film-limited-snr", type=float, default=None, help="a build whose PVDF contact SNR is below this is "
                   "film-limited: PC gets its input high-pass and refinement count margin where not given; 0: none is "
                   f"(default {FitConfig.film_limited_snr:g})")
    p.add_argument("--saturated-classes", default=None, help="comma-separated classes whose search also runs from a strongly "
                   "saturated start, or 'none' (default: SA1 on a build whose SingleTact noise is above --noisy-st-noise, else none)")
    p.add_argument("--noisy-st-noise", type=float, default=None, metavar="N", help="a build whose SingleTact sample noise "
                   "(N RMS on the contact-free baselines, from successive differences) is above this gets the noisy-SingleTact "
                   f"search (SA1's saturated start and restart) where not told otherwise (default {FitConfig.noisy_st_noise_n:g})")
    p.add_argument("--vr-distance-classes", default=None,
                   help="refined classes whose refinement is scored by the van Rossum distance normalised by TouchSim's own "
                   "variability (the held-out report's measure) instead of the paper's kernel distance, or 'none' (default: PC)")
    p.add_argument("--input-stage-classes", default=None,
                   help="classes whose input stage (low-pass cutoff, negative-part lead) is fitted, comma-separated or 'none' (default RA,PC)")
    p.add_argument("--max-ramp-conditions", type=int, default=None, help="fit on a seeded subsample of ramp conditions")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: all cores)")
    # --- Dask (docs/scale-out-dask.md)
    dask = p.add_mutually_exclusive_group()
    dask.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                      help="evaluate candidates on this Dask scheduler's workers (each reads DATASET_DIR at the same path)")
    dask.add_argument("--dask-workers", type=int, default=None, metavar="N",
                      help="evaluate candidates on a local Dask cluster of N worker processes")
    # --- end Dask
    p.add_argument("--init", type=Path, default=None, metavar="PARAMS.json",
                   help="start from this parameter file (its preprocessing settings and classes; unfitted classes are kept)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _weights_text(weights: dict[str, float]) -> str:
    return ",".join(f"{c}={w:g}" for c, w in weights.items())


def parse_windows(text: str) -> tuple[float, dict[str, float]]:
    """``"128"`` or ``"SA1=16,RA=16,PC=128"`` (a bare number in the list sets the default) ->
    (default window, per-class windows) in ms."""
    return _per_class_values(text, DEFAULT_WINDOW_MS, "W", " in ms")


def parse_restarts(text: str) -> dict[str, int]:
    """``"2"`` -> every class 2; ``"SA1=1,PC=2"`` -> those (the other classes none); ``"1,PC=2"`` ->
    PC 2, the others 1."""
    from .config import MAX_RESTARTS

    default, per_class = _per_class_values(text, None, "N", "")
    counts = {**({c: default for c in CLASSES} if default is not None else {}), **per_class}
    if not all(float(n).is_integer() and 0 <= n <= MAX_RESTARTS for n in counts.values()):
        raise argparse.ArgumentTypeError(f"{text!r}: restarts are whole numbers from 0 to {MAX_RESTARTS}")
    return {c: int(n) for c, n in counts.items()}


def parse_class_weights(text: str) -> dict[str, float]:
    """``"RA=3,PC=4"`` -> {class: weight} (``--refine``, ``--refine-sine-count-weights``); ``"none"`` -> {}."""
    if text.strip().lower() == "none":
        return {}
    default, per_class = _per_class_values(text, None, "K", "")
    if default is not None:
        raise argparse.ArgumentTypeError(f"{text!r}: expected CLS=K,... (a weight per class) or none")
    return per_class


def parse_highpass(text: str) -> dict[str, float]:
    """``"PC=5"`` -> {class: cutoff Hz} (``--highpass``); ``"none"`` -> {}."""
    from ..params import HIGHPASS_RANGE_HZ

    cutoffs = parse_class_weights(text)
    lo, hi = HIGHPASS_RANGE_HZ
    if not all(lo <= f <= hi for f in cutoffs.values()):
        raise argparse.ArgumentTypeError(f"{text!r}: high-pass cutoffs are from {lo:g} to {hi:g} Hz")
    return cutoffs


def _per_class_values(text: str, default: float | None, symbol: str, unit: str) -> tuple[float | None, dict[str, float]]:
    per_class: dict[str, float] = {}
    for tok in (t.strip() for t in text.split(",") if t.strip()):
        name, sep, value = tok.rpartition("=")
        try:
            w = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{tok!r}: expected {symbol} or CLS={symbol}{unit}") from None
        if not sep:
            default = w
        elif name.strip() in CLASSES:
            per_class[name.strip()] = w
        else:
            raise argparse.ArgumentTypeError(f"{tok!r}: unknown class {name.strip()!r} (expected one of {', '.join(CLASSES)})")
    return default, per_class


def _classes(text: str) -> tuple[str, ...]:
    """A comma-separated list of classes, or "none"."""
    return tuple(c.strip() for c in text.split(",") if c.strip() and c.strip().lower() != "none")


def run(args: argparse.Namespace) -> int:
    from ..params import EncoderParams
    from .config import FitConfig

    classes = _classes(args.classes)
    kw = {"classes": classes, "seed": args.seed, "progress": not args.quiet,
          "holdout": not args.no_holdout, "no_pvdf_classes": _classes(args.no_pvdf_classes)}
    if args.window_ms is not None:
        kw["window_ms"], kw["class_window_ms"] = args.window_ms
    for name, attr in (("generations", "max_generations"), ("popsize", "popsize"), ("restarts", "restarts"), ("kernel_ms", "kernel_ms"),
                       ("sine_weight", "sine_weight"), ("count_weight", "count_weight"), ("refine", "refine"),
                       ("refine_sine_count_weights", "refine_sine_count_weights"), ("highpass", "highpass_hz"),
                       ("refine_count_margins", "refine_count_margins"), ("gate_factor", "gate_factor"), ("weak_signal_snr", "weak_signal_snr"),
                       ("film_limited_snr", "film_limited_snr"),
                       ("noisy_st_noise", "noisy_st_noise_n"), ("max_ramp_conditions", "max_ramp_conditions"), ("workers", "workers")):
        v = getattr(args, name)
        if v is not None:
            kw[attr] = v
    for name in ("input_stage_classes", "segmented_count_classes", "vr_distance_classes", "saturated_classes", "excitatory_classes"):
        v = getattr(args, name)
        if v is not None:
            kw[name] = _classes(v)
    cfg = FitConfig(**kw)
    init = EncoderParams.load(args.init) if args.init else None
    outs = _outputs(args.datasets, args.out)
    jobs = [(d, o, cfg, init, len(outs) > 1) for d, o in zip(args.datasets, outs)]
    if args.scheduler is None and args.dask_workers is None:
        for job in jobs:
            _fit_one(*job)
        return 0
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    DaskExecutor, dask_client = _dask()
    with dask_client(args.scheduler, args.dask_workers) as client:
        if len(jobs) == 1:
            _fit_one(*jobs[0], executor=DaskExecutor.factory(client))
            return 0
        # several datasets side by side on the one cluster, each driven from its own process: cma
        # draws from NumPy's global RNG, so two fits in one process would interleave their draws
        with ProcessPoolExecutor(len(jobs), mp_context=mp.get_context("spawn")) as pool:
            for fut in [pool.submit(_fit_on_scheduler, client.scheduler.address, *job) for job in jobs]:
                fut.result()
    return 0


def _dask():
    """(DaskExecutor, dask_client), or an ImportError whose message is the install hint."""
    try:
        from .dask_executor import DaskExecutor, dask_client
    except ImportError as exc:
        raise ImportError(f"fitting on Dask needs the fit-dask extra: pip install -e '.[fit-dask]' ({exc})") from None
    return DaskExecutor, dask_client


def _fit_one(dataset: Path, out: Path, cfg: FitConfig, init: EncoderParams | None, prefix: bool,
             executor: ExecutorFactory | None = None) -> None:
    """Fit one dataset, write its parameter file and print the summary (log lines prefixed with
    the dataset's folder name when ``prefix``)."""
    from .fit import fit_dataset

    def log(msg: str) -> None:
        print(f"{dataset.name}: {msg}" if prefix else msg, file=sys.stderr)

    res = fit_dataset(dataset, cfg, init=init, log=log, executor=executor)
    res.params.save(out)
    _summary(res, out)


def _fit_on_scheduler(address: str, *job) -> None:
    """A driver process of its own: fit one dataset on the Dask scheduler at ``address``."""
    from .dask_executor import DaskExecutor, dask_client

    with dask_client(address) as client:
        _fit_one(*job, executor=DaskExecutor.factory(client))


def _outputs(datasets: list[Path], out: Path) -> list[Path]:
    """The parameter file of each dataset: ``out`` itself for one, ``out/<folder name>.json`` for several."""
    if len(datasets) == 1:
        if out.parent and not out.parent.exists():
            raise ValueError(f"output folder {out.parent} does not exist")
        return [out]
    names = [d.resolve().name for d in datasets]
    if len(set(names)) < len(names):
        raise ValueError(f"several datasets share a folder name ({', '.join(names)}); fit them separately")
    if not out.is_dir():
        raise ValueError(f"with several datasets --out must be an existing folder, got {out}")
    return [out / f"{n}.json" for n in names]


def _summary(res: FitResult, out: Path) -> None:
    print(f"fitted {', '.join(res.classes)} on {res.n_train} training trials in {res.seconds:.0f} s -> {out}")
    for c, f in res.classes.items():
        tr = f.train.total if f.train else float("nan")
        va = f"{f.validation.total:.4f}" if f.validation else "- (none held out)"
        if f.search is not None:
            s = f.search
            print(f"  {c}: search loss start {s.start_loss:.4f} ({s.generations} generations, {s.evaluations} evaluations, {s.seconds:.0f} s), then")
        print(f"  {c}: {'refinement ' if f.search is not None else ''}loss start {f.start_loss:.4f} -> train {tr:.4f}, held-out {va} "
              f"({f.generations} generations, {f.evaluations} evaluations, {f.seconds:.0f} s)")
