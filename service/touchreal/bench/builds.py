"""Fit fidelity across sensor builds: simulate, fit and score each build on its own held-out split.

Per build (``data/builds.json``, or JSON files): ``touchreal simulate ramp sine`` with rig-v1's
counts (896 ramps, 100 sines: the calibration set of a real rig), ``touchreal fit`` with its
defaults (train/held-out split by repeat; the fit measures the build's profile and resolves its plan
from it, :mod:`touchreal.fitting.policy`), then ``touchreal evaluate`` on the held-out trials. Each
row shows the build's profile and the policy's rules it met, from the fit's provenance.
Per class, the van Rossum ratio (inter / intra, tau 1 ms, the report's) and the mean count error over conditions,
against the targets of a fit that transfers: count error <= 15 % for SA1 and RA and <= 25 % for PC,
VR ratio <= 1.2 / 1.3 / 1.5. Each build takes a full fit (about 9 min on 2 idle cores).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from ..analysis.metrics import TARGETS as REPORT_TARGETS
from ..fitting.describe import rule_summary
from ..fitting.policy import RULES
from ..fitting.profile import MEASURES
from ..settings import CLASSES

#: VR ratio a fit must stay within on a build's held-out trials: the evaluation report's bounds
VR_MAX = REPORT_TARGETS["vr_ratio_max"]
#: count error likewise: the report's bound, PC's looser (its turning-point spikes vary most with the film)
COUNT_MAX = {c: REPORT_TARGETS["count_error_max"] for c in CLASSES} | {"PC": 0.25}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--builds", default="nominal,weak-film-60hz,noisy-amplifier,stiff-film-slow-rig",
                   help="comma-separated shipped build names or JSON build files (docs/simulator.md)")
    p.add_argument("--trials", default="ramp=896,sine=100", help="calibration set per build (touchreal simulate "
                   "--trials; default rig-v1's ramps and sines)")
    p.add_argument("--seed", type=int, default=0, help="simulation, split and CMA-ES seed (default 0)")
    p.add_argument("--fit-args", default="", help="extra `touchreal fit` options, e.g. '--recipe short.json'")
    p.add_argument("--work", type=Path, default=None, help="keep datasets, parameters and reports here "
                   "(default: a temporary folder)")


def _score(metrics: dict) -> dict[str, tuple[float, float]]:
    """Per class (count error, VR ratio) over the held-out conditions."""
    out = {}
    for c in CLASSES:
        s = metrics["mapping"].get(c, {}).get("all", {})
        out[c] = (float(s.get("count_error_mean", float("nan"))), float(s.get("ratio_inter_intra", float("nan"))))
    return out


def _one(build: str, work: Path, args: argparse.Namespace) -> tuple[dict[str, tuple[float, float]], float, dict]:
    from ..cli import main

    name = Path(build).stem
    data, params, report = work / name, work / f"{name}.json", work / f"{name}-report"
    if main(["simulate", "ramp", "sine", "--trials", args.trials, "--build", build, "--seed", str(args.seed),
             "--out", str(data), "--quiet"]) != 0:
        raise SystemExit(f"simulate failed for build {build}")
    t0 = time.monotonic()
    if main(["fit", str(data), "--out", str(params), "--seed", str(args.seed), "--quiet", *args.fit_args.split()]) != 0:
        raise SystemExit(f"fit failed for build {build}")
    fit_s = time.monotonic() - t0
    if main(["evaluate", str(data), "--params", str(params), "--out", str(report), "--no-sweep", "--no-spatial",
             "--quiet"]) != 0:
        raise SystemExit(f"evaluate failed for build {build}")
    return _score(json.loads((report / "metrics.json").read_text())), fit_s, json.loads(params.read_text())["provenance"]


def _profile_cells(prov: dict) -> list[str]:
    """The fit's measures of the build (its profile), each in its display unit under its header."""
    cells = []
    for m, (label, scale, unit) in MEASURES.items():
        v = prov["profile"].get(m)
        cells.append(f"{'-' if v is None else f'{v * scale:.1f}':>{len(label + unit)}}")
    return cells


def run(args: argparse.Namespace) -> int:
    builds = [b for b in args.builds.split(",") if b]
    print(f"Fit fidelity across sensor builds: simulate ({args.trials}), `touchreal fit` "
          f"{args.fit_args or '(defaults)'}, evaluate on each build's held-out trials (seed {args.seed})")
    print("targets: count error <= " + ", ".join(f"{c} {COUNT_MAX[c]:.0%}" for c in CLASSES)
          + "; VR ratio <= " + ", ".join(f"{c} {VR_MAX[c]:g}" for c in CLASSES))
    head = "  ".join(f"{c + ' count':>9}  {c + ' VR':>6}" for c in CLASSES)
    profile_head = "  ".join(f"{label}{unit}" for label, _, unit in MEASURES.values())
    print(f"\n   {'build':<22}  {'fit':>6}  {profile_head}  {head}  targets  rules")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        met_all = True
        for build in builds:
            score, fit_s, prov = _one(build, work, args)
            cells, met = [], []
            for c in CLASSES:
                ce, vr = score[c]
                ok = ce <= COUNT_MAX[c] and vr <= VR_MAX[c]
                met.append(ok)
                cells.append(f"{ce:9.1%}  {vr:6.2f}")
            met_all &= all(met)
            missed = [c for c, ok in zip(CLASSES, met) if not ok]
            print(f"   {Path(build).stem:<22}  {fit_s / 60:5.1f}m  {'  '.join(_profile_cells(prov))}  {'  '.join(cells)}  "
                  f"{'met' if not missed else 'missed:' + ','.join(missed)}  {','.join(prov['rules']) or '-'}", flush=True)
    print("profile: the fit's measures of the build; rules: those its profile met (touchreal fit --plan shows a plan):")
    for rule in RULES:
        print(f"  {rule_summary(rule)}")
    print(f"\nevery build within the targets: {'yes' if met_all else 'no'}")
    return 0
