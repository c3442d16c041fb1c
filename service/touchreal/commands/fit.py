"""``touchreal fit DATASET_DIR --out PARAMS.json``: fit the encoder to a dataset's TouchSim references."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..settings import CLASSES, DEFAULT_WINDOW_MS

if TYPE_CHECKING:
    from ..params import EncoderParams
    from ..fitting.config import FitConfig
    from ..fitting.executor import ExecutorFactory
    from ..fitting.fit import FitResult


def register(sub: argparse._SubParsersAction) -> None:
    from ..fitting.describe import rule_summary
    from ..fitting.plan import ClassPlan, FitPlan, RefinePlan
    from ..fitting.policy import RULES

    p = sub.add_parser(
        "fit",
        help="fit SA1/RA/PC encoder parameters to a dataset's TouchSim reference spike trains",
        description="Per afferent class, CMA-ES on the paper's objective (eqs. 1-10) over the ramp and sine "
        "training trials (split by repeat; the rest is held out for `touchreal evaluate`). The fit measures the "
        "build's profile and resolves its plan: the defaults, then the rules the profile meets ("
        + "; ".join(rule_summary(r) for r in RULES) + "), then the recipe. --plan prints the plan and its reasons. "
        "See docs/fitting.md.",
    )
    p.add_argument("datasets", type=Path, nargs="+", metavar="DATASET_DIR",
                   help="dataset folder (manifest.json + trials/); several (one per sensor) are fitted one after another, "
                   "or side by side on one Dask cluster")
    p.add_argument("--out", type=Path, default=None, metavar="PARAMS.json",
                   help="parameter file to write; with several datasets a folder, receiving DATASET_DIR-name.json each "
                   "(required unless --plan)")
    p.add_argument("--classes", default=",".join(CLASSES), help="comma-separated classes to fit (default: all)")
    p.add_argument("--window-ms", type=parse_windows, default=None, metavar="W|CLS=W,...",
                   help="causal PVDF window (ms) of every class, e.g. 128, or per class, e.g. SA1=16,RA=16,PC=128 "
                   f"(classes not named take a bare number given in the list, else {DEFAULT_WINDOW_MS:g}); default: the "
                   "windows of the shipped parameters (the fast path); wins over the recipe's windows")
    p.add_argument("--seed", type=int, default=0, help="seed of the train/held-out split and of CMA-ES (default 0)")
    p.add_argument("--no-holdout", action="store_true",
                   help="train on every ramp/sine trial (no held-out half; evaluate on a separate recording)")
    p.add_argument("--recipe", type=Path, default=None, metavar="FILE.json",
                   help="a JSON object overriding fields of the resolved plan, nested as --plan and the file's provenance "
                   'show it, e.g. {"generations": 50, "classes": {"PC": {"highpass_hz": null}}}; fields: '
                   + ", ".join(f for f in FitPlan.model_fields if f != "classes") + "; per class (classes.CLS): "
                   + ", ".join(ClassPlan.model_fields) + "; refine: " + ", ".join(RefinePlan.model_fields)
                   + ". An unknown field or a value out of range is an error")
    p.add_argument("--plan", action="store_true",
                   help="print each dataset's plan (its build profile, the rules that apply, every field and what set it) and exit")
    p.add_argument("--init", type=Path, default=None, metavar="PARAMS.json",
                   help="start from this parameter file (its preprocessing settings and classes; unfitted classes are kept)")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    # --- Dask (docs/scale-out-dask.md)
    dask = p.add_mutually_exclusive_group()
    dask.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                      help="evaluate candidates on this Dask scheduler's workers (each reads DATASET_DIR at the same path)")
    dask.add_argument("--dask-workers", type=int, default=None, metavar="N",
                      help="evaluate candidates on a local Dask cluster of N worker processes")
    # --- end Dask
    p.set_defaults(func=run)


def parse_windows(text: str) -> tuple[float, dict[str, float]]:
    """``"128"`` or ``"SA1=16,RA=16,PC=128"`` (a bare number in the list sets the default) ->
    (default window, per-class windows) in ms."""
    default, per_class = DEFAULT_WINDOW_MS, {}
    for tok in (t.strip() for t in text.split(",") if t.strip()):
        name, sep, value = tok.rpartition("=")
        try:
            w = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{tok!r}: expected W or CLS=W in ms") from None
        if not sep:
            default = w
        elif name.strip() in CLASSES:
            per_class[name.strip()] = w
        else:
            raise argparse.ArgumentTypeError(f"{tok!r}: unknown class {name.strip()!r} (expected one of {', '.join(CLASSES)})")
    return default, per_class


def window_recipe(default_ms: float, class_ms: dict[str, float], classes: tuple[str, ...]) -> dict[str, Any]:
    """The plan overrides of ``--window-ms``: the preprocessing window, and every fitted class's
    (``class_ms``, else the default), in ms."""
    return {"window_ms": default_ms, "classes": {c: {"window_ms": class_ms.get(c, default_ms)} for c in classes}}


def load_recipe(path: Path) -> dict[str, Any]:
    """A recipe file: a JSON object of plan overrides."""
    try:
        recipe = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"recipe {path}: not JSON ({exc})") from None
    if not isinstance(recipe, dict):
        raise ValueError(f"recipe {path}: expected a JSON object of plan fields")
    return recipe


def _classes(text: str) -> tuple[str, ...]:
    """A comma-separated list of classes."""
    return tuple(c.strip() for c in text.split(",") if c.strip())


def run(args: argparse.Namespace) -> int:
    from ..params import EncoderParams
    from ..fitting.config import FitConfig
    from ..fitting.plan import PlanError, merged

    classes = _classes(args.classes)
    recipe = load_recipe(args.recipe) if args.recipe else {}
    if args.window_ms is not None:
        recipe = merged(recipe, window_recipe(*args.window_ms, classes))
    try:
        cfg = FitConfig(classes=classes, seed=args.seed, holdout=not args.no_holdout, recipe=recipe, workers=args.workers,
                        progress=not args.quiet)
    except PlanError as exc:
        given = [x for x, on in ((f"--recipe {args.recipe}", args.recipe), ("--window-ms", args.window_ms)) if on is not None]
        raise PlanError(f"the plan's overrides ({', '.join(given)}): {exc}") from None
    init = EncoderParams.load(args.init) if args.init else None
    if args.plan:
        _print_plans(args.datasets, cfg, init)
        return 0
    if args.out is None:
        raise ValueError("--out is required (or --plan, to print the plan without fitting)")
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


def _print_plans(datasets: list[Path], cfg: FitConfig, init: EncoderParams | None) -> None:
    """Print the plan resolved for each dataset, without fitting."""
    from ..fitting.describe import plan_text
    from ..fitting.executor import FitSource
    from ..fitting.fit import measure

    for d in datasets:
        if len(datasets) > 1:
            print(f"== {d}")
        print(plan_text(measure(FitSource(str(d), cfg, init)).resolution))


def _dask():
    """(DaskExecutor, dask_client), or an ImportError whose message is the install hint."""
    try:
        from ..fitting.dask_executor import DaskExecutor, dask_client
    except ImportError as exc:
        raise ImportError(f"fitting on Dask needs the fit-dask extra: pip install -e '.[fit-dask]' ({exc})") from None
    return DaskExecutor, dask_client


def _fit_one(dataset: Path, out: Path, cfg: FitConfig, init: EncoderParams | None, prefix: bool,
             executor: ExecutorFactory | None = None) -> None:
    """Fit one dataset, write its parameter file and print the summary (log lines prefixed with
    the dataset's folder name when ``prefix``)."""
    from ..fitting.fit import fit_dataset

    def log(msg: str) -> None:
        print(f"{dataset.name}: {msg}" if prefix else msg, file=sys.stderr)

    res = fit_dataset(dataset, cfg, init=init, log=log, executor=executor)
    res.params.save(out)
    _summary(res, out)


def _fit_on_scheduler(address: str, *job) -> None:
    """A driver process of its own: fit one dataset on the Dask scheduler at ``address``."""
    from ..fitting.dask_executor import DaskExecutor, dask_client

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
