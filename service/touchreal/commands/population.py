"""``touchreal population plan|validate``: afferent populations (docs/population.md).

``plan`` prints the population plan a skin would run with, its model variants matched to
TouchSim's single-unit models for the parameter set (``--set FIELD=JSON`` overrides a field);
save it and pass it to ``touchreal serve --population PLAN.json``.
``validate`` compares populations over simulated taxel patches of several pitches with TouchSim's
responses for afferents at the same positions, depths and models, and writes metrics.json,
report.md and figures to OUT.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..params import EncoderParams, default_params


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("population", help="afferent populations: print a plan, validate against TouchSim",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ps = p.add_subparsers(dest="population_command", required=True, metavar="ACTION")
    plan = ps.add_parser("plan", help="print a population plan (JSON) with model variants matched for the parameters")
    plan.add_argument("--params", type=Path, help="parameter file (default: the shipped parameters)")
    plan.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                      help='override a plan field, e.g. --set seed=3 --set \'density_per_cm2={"SA1": 70, "RA": 140, "PC": 25}\'')
    plan.set_defaults(func=run_plan)
    val = ps.add_parser("validate", help="population against TouchSim over simulated patches; report to OUT")
    val.add_argument("--params", type=Path, help="parameter file (default: the shipped parameters)")
    val.add_argument("--plan", type=Path, help="population plan JSON (default: `population plan`'s)")
    val.add_argument("--pitches", default="3,5,10", help="taxel pitches in mm (default 3,5,10)")
    val.add_argument("--side", type=int, default=4, help="taxels per side of the patch (default 4)")
    val.add_argument("--out", type=Path, required=True, help="output folder")
    val.set_defaults(func=run_validate)


def _params(path: Path | None) -> EncoderParams:
    return EncoderParams.load(path) if path else default_params()


def run_plan(args: argparse.Namespace) -> int:
    from ..fitting.variants import resolve_plan

    print(resolve_plan(_params(args.params), args.set).to_json())
    return 0


def run_validate(args: argparse.Namespace) -> int:
    from ..analysis.population_report import evaluate_population
    from ..fitting.variants import resolve_plan

    params = _params(args.params)
    pitches = [float(x) for x in args.pitches.split(",") if x]
    if not pitches or any(not 0.5 <= p <= 50 for p in pitches):
        raise ValueError("--pitches: comma-separated pitches within 0.5-50 mm")
    if not 1 <= args.side <= 16:
        raise ValueError("--side must be within 1-16")
    doc = evaluate_population(params, resolve_plan(params, path=args.plan), args.out, pitches, args.side)
    for pitch, r in doc["pitches"].items():
        for cls, m in r["classes"].items():
            print(f"{pitch:>4} mm {cls:<3} map r {m['map_r']:.2f}  count error {100 * m['count_error']:.0f} %  "
                  f"VR ratio {m['vr_ratio']:.2f}  extent {m['extent_mm2']:.0f} mm^2 (TouchSim {m['extent_touchsim_mm2']:.0f})")
    print(f"report: {args.out / 'report.md'}")
    return 0
