"""``touchreal evaluate DATASET_DIR --params PARAMS.json --out REPORT_DIR``: the evaluation report."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="compare TouchReal with the TouchSim references on held-out trials; write report.md, metrics.json, figures",
        description="Reproduces the paper's evaluation (Figs. 7-12, Tables 1-3) on the dataset's held-out trials. "
        "See docs/evaluation.md.",
    )
    p.add_argument("dataset", type=Path, metavar="DATASET_DIR", help="dataset folder (manifest.json + trials/)")
    p.add_argument("--params", type=Path, default=None, metavar="PARAMS.json", help="parameter file (default: the shipped defaults)")
    p.add_argument("--out", type=Path, required=True, metavar="REPORT_DIR", help="folder for report.md, metrics.json and PNGs")
    p.add_argument("--split", choices=("auto", "all", "train"), default="auto",
                   help="auto: the held-out trials recorded by `touchreal fit` (all trials if fitted elsewhere); all: every trial; "
                   "train: the fit's training trials (to choose fit settings without looking at held-out trials)")
    p.add_argument("--ramp-condition", default=None, help="ramp condition of Fig. 7")
    p.add_argument("--sweep-ramp-conditions", type=int, default=64,
                   help="ramp conditions in the window sweep (Fig. 12), 0 = all (default 64)")
    p.add_argument("--no-sweep", action="store_true", help="skip the causal window sweep (Fig. 12)")
    p.add_argument("--latency-trials", type=int, default=1,
                   help="held-out ramp trials replayed in 1 ms chunks to measure each class's emission - stamp (0: algorithmic only)")
    p.add_argument("--no-spatial", action="store_true", help="skip the spatial analysis (Figs. 10-11)")
    p.add_argument("--population", default=None, metavar="PITCHES",
                   help="also the population section: the default population plan against TouchSim over simulated "
                   "taxel patches of these pitches (mm, e.g. 3,5,10), in REPORT_DIR/population (docs/population.md)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..params import EncoderParams, default_params
    from ..analysis.report import EvalConfig, evaluate

    params = EncoderParams.load(args.params) if args.params else default_params()
    cfg = EvalConfig(
        split=args.split,
        ramp_condition=args.ramp_condition,
        sweep_max_ramp_conditions=None if args.sweep_ramp_conditions == 0 else args.sweep_ramp_conditions,
        with_sweep=not args.no_sweep,
        with_spatial=not args.no_spatial,
        latency_trials=max(0, args.latency_trials),
        progress=not args.quiet,
    )

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    pitches = [float(x) for x in args.population.split(",") if x] if args.population else []
    if args.population is not None and (not pitches or any(not 0.5 <= p <= 50 for p in pitches)):
        raise ValueError("--population: comma-separated taxel pitches within 0.5-50 mm")
    m = evaluate(args.dataset, params, args.out, cfg, log=log)
    if pitches:
        from ..analysis.population_report import evaluate_population
        from ..fitting.variants import resolve_plan

        log("population section ...")
        evaluate_population(params, resolve_plan(params), args.out / "population", pitches)
        with (args.out / "report.md").open("a") as fp:
            fp.write("\n## Afferent populations\n\nThe population against TouchSim's own population response, its "
                     "raster and rate maps: [population/report.md](population/report.md).\n")
    failed = [k for k, v in m["targets"].items() if not v["pass"]]
    print(f"report: {args.out / 'report.md'}  ({len(m['targets']) - len(failed)}/{len(m['targets'])} targets met"
          + (f"; not met: {', '.join(failed)}" if failed else "") + ")")
    return 0
