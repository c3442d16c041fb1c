"""A population against TouchSim's own population response, over a simulated multi-taxel patch.

For each taxel pitch, a square patch of taxels (:func:`~touchreal.simulator.patch.grid_patch`,
sensors as wide as the pitch) carries a population placed by the plan. Probe indentations (a
ramp-and-hold and two vibration bursts) at several positions (a taxel's centre, the middle of an
edge between two taxels, the corner of four, and an off-grid point) are recorded by the simulated
patch and encoded by the population; TouchSim's reference model computes, from the commanded
indentation, the response of an afferent at each population afferent's position, depth and model.

Per class and pitch:

* ``map_r``: Pearson correlation of the two populations' spike counts over the class's afferents
  (the population rate map), averaged over the probe conditions;
* ``count_error``: |total count - TouchSim's total| / TouchSim's total over every condition;
* ``vr_ratio``: for afferents within 2 mm of the probe, the van Rossum distance (tau 1 ms, as
  ``touchreal evaluate``) of each afferent's train to TouchSim's noisy repeats, over the mean
  distance between those repeats (1 = as close as TouchSim is to itself);
* ``extent_mm2``: the area over which the class responds to a ramp at a taxel's centre
  (afferents with a spike, times the area per afferent), beside TouchSim's;
* ``extents``: the same area for every stimulus at a taxel's centre, ``{stimulus: [ours, TouchSim]}``
  (which class responds wider depends on the stimulus, in TouchSim too).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..params import EncoderParams
from ..reference.constants import load_constants
from ..reference.model import ReferenceModel
from ..settings import CLASSES
from ..simulator.patch import grid_patch, patch_skin, probe_recording
from ..simulator.stimuli import RampHold, SineBurst
from ..stream import encode_chunks
from ..population.encoder import Population
from ..population.layout import PopulationPlan
from . import spiketrains as stn
from .metrics import VR_TAU_S

NEAR_MM = 2.0  #: afferents this close to the probe enter the VR ratio
VR_REPEATS = 3  #: noisy TouchSim repeats per near afferent


def probe_positions(pitch_mm: float) -> dict[str, tuple[float, float]]:
    """Probe centres over a 4 x 4 patch centred on (0, 0): taxel centre, edge, corner, off-grid."""
    h = pitch_mm / 2.0
    return {"centre": (h, h), "edge": (h, 0.0), "corner": (0.0, 0.0), "off-grid": (0.3 * pitch_mm, -0.8 * pitch_mm)}


#: the fast vibration (Hz): in PC's and RA's range, and off every mains harmonic a build may notch (50 Hz mains:
#: 150, 250 Hz; 60 Hz: 180, 300 Hz), as the dataset's spatial sines: a burst at 150 Hz is removed with the hum by
#: the shipped calibration's third-harmonic notch (RA 0.20x, PC 0.09x TouchSim's spikes at 3 mm, against 1.06x and
#: 0.37x at 160 Hz), which would measure the notch, not the population
FAST_HZ = 165.0


def probe_stimuli() -> dict[str, object]:
    return {"ramp 1 mm": RampHold(1.0, 20.0, 20.0, 0.5), "sine 40 Hz": SineBurst.calibrated(40.0, burst_s=0.5),
            f"sine {FAST_HZ:g} Hz": SineBurst.calibrated(FAST_HZ, burst_s=0.5)}


@dataclass
class Condition:
    """One probe condition: both populations' trains (afferent -> spike times, s)."""

    probe: str
    stimulus: str
    probe_xy_mm: tuple[float, float]
    ours: list[np.ndarray]
    touchsim: list[np.ndarray]  # noiseless
    near: dict[int, list[np.ndarray]]  # afferent -> noisy TouchSim repeats


def touchsim_response(trace_mm: np.ndarray, probe_xy_mm, pop: Population, *, noisy: bool, repeats: int = 1, seed: int = 0,
                      afferents: np.ndarray | None = None) -> list[list[np.ndarray]]:
    """TouchSim trains (per afferent, per repeat) of the population's afferents, each with its own
    TouchSim model (variant index = TouchSim's model within the class) at its position and depth."""
    c = load_constants()
    lay = pop.layout
    ids = np.arange(len(lay)) if afferents is None else np.asarray(afferents)
    out: list[list[np.ndarray]] = [[] for _ in range(len(lay))]
    model_of = {(int(k), int(i)): m for m, (k, i) in enumerate(zip(c.class_of_model, c.model_index))}
    for m in range(c.n_models):
        sel = ids[[model_of[(int(lay.cls[a]), int(lay.model[a]))] == m for a in ids]] if ids.size else ids
        if sel.size == 0:
            continue
        one = replace(c, params=c.params[[m]], model_class=c.model_class[[m]], model_index=c.model_index[[m]],
                      class_of_model=c.class_of_model[[m]])
        resp = ReferenceModel(pin_radius_mm=pop.plan.probe_radius_mm, constants=one).simulate(
            trace_mm, probe_xy_mm=probe_xy_mm, afferent_xy_mm=lay.xy_mm[sel], repeats=repeats, noisy=noisy, rng=seed + m)
        for j, a in enumerate(sel):
            out[a] = [resp.train(r, j, 0) for r in range(resp.repeats)]
    return out


def run_patch(params: EncoderParams, plan: PopulationPlan, pitch_mm: float, side: int = 4, seed: int = 0) -> tuple[Population, list[Condition]]:
    """Every probe condition over a ``side`` x ``side`` patch of ``pitch_mm`` (see the module doc)."""
    taxels = grid_patch(side, pitch_mm)
    pop = Population.build(taxels, plan)
    skin = patch_skin(pitch_mm)
    conds = []
    for i, (pname, xy) in enumerate(probe_positions(pitch_mm).items()):
        for j, (sname, stim) in enumerate(probe_stimuli().items()):
            rec = probe_recording(stim, xy, taxels, skin=skin, seed=seed + 10 * i + j)
            ev = encode_chunks(params, [rec.raw], len(taxels), population=pop)
            ours = [ev.t_s[ev.taxel == a] - rec.onset_s for a in range(len(pop))]
            ts = [r[0] - rec.onset_s for r in touchsim_response(rec.cmd_depth, xy, pop, noisy=False)]
            near = np.flatnonzero(np.hypot(*(pop.layout.xy_mm - np.asarray(xy)).T) <= NEAR_MM)
            noisy = touchsim_response(rec.cmd_depth, xy, pop, noisy=True, repeats=VR_REPEATS, seed=seed + 100 * i + j,
                                      afferents=near)
            conds.append(Condition(pname, sname, xy, ours, ts, {int(a): [t - rec.onset_s for t in noisy[a]] for a in near}))
    return pop, conds


def summarize(pop: Population, conds: list[Condition], pitch_mm: float) -> dict[str, dict[str, float]]:
    """Per class: map_r, count_error, vr_ratio, extent_mm2 and TouchSim's extent (see the module doc)."""
    lay = pop.layout
    out = {}
    for k, cls in enumerate(CLASSES):
        ids = np.flatnonzero(lay.cls == k)
        if ids.size == 0:
            continue
        rs, n_ours, n_ts, inter, intra = [], 0, 0, [], []
        for c in conds:
            a = np.array([c.ours[i].size for i in ids], float)
            b = np.array([c.touchsim[i].size for i in ids], float)
            n_ours, n_ts = n_ours + a.sum(), n_ts + b.sum()
            if a.std() > 0 and b.std() > 0:
                rs.append(float(np.corrcoef(a, b)[0, 1]))
            for i, reps in c.near.items():
                if lay.cls[i] != k:
                    continue
                inter.extend(stn.vr_distance(c.ours[i], r, VR_TAU_S) for r in reps)
                intra.extend(stn.vr_distance(reps[p], reps[q], VR_TAU_S) for p in range(len(reps)) for q in range(p + 1, len(reps)))
        per_afferent_mm2 = 100.0 / pop.plan.density_per_cm2[cls]
        ramp = next(c for c in conds if c.probe == "centre" and c.stimulus.startswith("ramp"))
        extents = {c.stimulus: [float(sum(t[i].size > 0 for i in ids) * per_afferent_mm2) for t in (c.ours, c.touchsim)]
                   for c in conds if c.probe == "centre"}
        out[cls] = {
            "map_r": float(np.mean(rs)) if rs else float("nan"),
            "count_error": float(abs(n_ours - n_ts) / n_ts) if n_ts else float("nan"),
            "vr_ratio": float(np.mean(inter) / np.mean(intra)) if intra and np.mean(intra) > 0 else float("nan"),
            "extent_mm2": float(sum(ramp.ours[i].size > 0 for i in ids) * per_afferent_mm2),
            "extent_touchsim_mm2": float(sum(ramp.touchsim[i].size > 0 for i in ids) * per_afferent_mm2),
            "extents": extents,
            "spikes": int(n_ours),
            "spikes_touchsim": int(n_ts),
        }
    return out
