"""The population section of the evaluation: metrics.json, report.md and figures in one folder.

Figures (PNG): per pitch, a raster of the population's spikes beside TouchSim's for the ramp at a
taxel's centre (afferents sorted by class, then distance to the probe), and per class the rate
maps (spike count of each afferent at its position) of both for the same condition.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..params import EncoderParams
from ..population.layout import PopulationPlan
from ..settings import CLASSES
from .figures import _save, plt
from .population import Condition, run_patch, summarize

CLASS_COLORS = {"SA1": "#2ca02c", "RA": "#1f77b4", "PC": "#d62728"}


def raster(path: Path, pop, cond: Condition) -> Path:
    """TouchReal's population (left) beside TouchSim's (right), one row per afferent."""
    lay = pop.layout
    dist = np.hypot(*(lay.xy_mm - np.asarray(cond.probe_xy_mm)).T)
    order = np.lexsort((dist, lay.cls))
    fig, axes = plt.subplots(1, 2, figsize=(11, 6), sharey=True)
    for ax, trains, title in ((axes[0], cond.ours, "TouchReal population"), (axes[1], cond.touchsim, "TouchSim")):
        for row, a in enumerate(order):
            t = trains[a]
            if t.size:
                ax.plot(t, np.full(t.size, row), "|", ms=2, color=CLASS_COLORS[CLASSES[lay.cls[a]]])
        ax.set_title(f"{title}: {cond.stimulus} at the {cond.probe}")
        ax.set_xlabel("time from onset (s)")
    axes[0].set_ylabel("afferent (by class, then distance to the probe)")
    return _save(fig, path)


def rate_maps(path: Path, pop, cond: Condition) -> Path:
    """Per class, each afferent's spike count at its position: TouchReal (top) and TouchSim (bottom)."""
    lay = pop.layout
    fig, axes = plt.subplots(2, len(CLASSES), figsize=(4 * len(CLASSES), 7.5), squeeze=False)
    for k, cls in enumerate(CLASSES):
        ids = np.flatnonzero(lay.cls == k)
        counts = [np.array([cond.ours[a].size for a in ids]), np.array([cond.touchsim[a].size for a in ids])]
        vmax = max(1, max(int(c.max(initial=0)) for c in counts))
        for row, (c, who) in enumerate(zip(counts, ("TouchReal", "TouchSim"))):
            ax = axes[row, k]
            sc = ax.scatter(lay.xy_mm[ids, 0], lay.xy_mm[ids, 1], c=c, s=10, cmap="viridis", vmin=0, vmax=vmax)
            ax.scatter(pop.taxels_xy_mm[:, 0], pop.taxels_xy_mm[:, 1], marker="+", color="grey", s=30)
            ax.plot(*cond.probe_xy_mm, "rx", ms=8)
            ax.set_title(f"{cls} {who}")
            ax.set_aspect("equal")
            fig.colorbar(sc, ax=ax, label="spikes")
    return _save(fig, path)


def evaluate_population(params: EncoderParams, plan: PopulationPlan, out: Path, pitches_mm: Sequence[float] = (3.0, 5.0, 10.0),
                        side: int = 4, seed: int = 0) -> dict:
    """Run the validation at every pitch, write ``out``/metrics.json, report.md and figures."""
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    figures = {}
    for pitch in pitches_mm:
        pop, conds = run_patch(params, plan, pitch, side, seed)
        results[f"{pitch:g}"] = {"afferents": {c: int((pop.layout.cls == k).sum()) for k, c in enumerate(CLASSES)},
                                 "classes": summarize(pop, conds, pitch)}
        ramp = next(c for c in conds if c.probe == "centre" and c.stimulus.startswith("ramp"))
        figures[f"{pitch:g}"] = [raster(out / f"raster_{pitch:g}mm.png", pop, ramp).name,
                                 rate_maps(out / f"rate_maps_{pitch:g}mm.png", pop, ramp).name]
    doc = {"created": datetime.now(timezone.utc).isoformat(timespec="seconds"), "side": side, "seed": seed,
           "plan": json.loads(plan.to_json()), "pitches": results, "figures": figures}
    (out / "metrics.json").write_text(json.dumps(doc, indent=1))
    (out / "report.md").write_text(render(doc))
    return doc


def render(doc: dict) -> str:
    lines = [f"# Population against TouchSim ({doc['side']} x {doc['side']} taxels, seed {doc['seed']})", "",
             "Per class: rate-map correlation (target >= 0.9), total spike-count error (target <= 15 %), VR distance "
             "ratio of afferents within 2 mm of the probe (1 = as close as TouchSim's repeats), and the area that "
             "responds to a 1 mm ramp at a taxel's centre beside TouchSim's.", "",
             "| pitch (mm) | class | afferents | map r | count error | VR ratio | extent (mm^2) | TouchSim extent (mm^2) |",
             "|---|---|---|---|---|---|---|---|"]
    for pitch, r in doc["pitches"].items():
        for cls, m in r["classes"].items():
            lines.append(f"| {pitch} | {cls} | {r['afferents'][cls]} | {m['map_r']:.2f} | {100 * m['count_error']:.0f} % | "
                         f"{m['vr_ratio']:.2f} | {m['extent_mm2']:.0f} | {m['extent_touchsim_mm2']:.0f} |")
    lines += ["", "Area (mm^2) that responds to each stimulus at a taxel's centre, TouchReal / TouchSim:", ""]
    stimuli = [k for r in doc["pitches"].values() for m in r["classes"].values() for k in m.get("extents", {})]
    stimuli = list(dict.fromkeys(stimuli))
    lines += ["| pitch (mm) | class | " + " | ".join(stimuli) + " |", "|---|---|" + "---|" * len(stimuli)]
    for pitch, r in doc["pitches"].items():
        for cls, m in r["classes"].items():
            ext = m.get("extents", {})
            cells = [f"{ext[k][0]:.0f} / {ext[k][1]:.0f}" if k in ext else "" for k in stimuli]
            lines.append(f"| {pitch} | {cls} | " + " | ".join(cells) + " |")
    lines.append("")
    for pitch, names in doc["figures"].items():
        lines += [f"## {pitch} mm", ""] + [f"![{n}]({n})" for n in names] + [""]
    return "\n".join(lines)
