"""TouchSim's single-unit models mapped onto TouchReal's input stage, one gain per model.

TouchSim fits 4 SA1, 9 RA and 4 PC single-unit models; within a class they differ above all in
sensitivity (the same stimulus drives one unit to a few spikes and another to many). TouchReal
fits one parameter set per class to the class's models together, from the sensor's channels.
A **variant** is that class's parameter set with every input weight scaled by one gain, chosen
so that the variant's spike count relative to its class's fitted set equals the TouchSim model's
count relative to its class's mean model, over a standard probe set (ramp-and-holds and
vibration bursts at the afferent's location, :data:`STANDARD_SET`).

Why a gain and not a refit per model: a refit of 13 parameters per model against the few
reference trains of one unit would overfit the rig and take minutes per model; the gain carries
the first-order difference between units (their relative sensitivity) through the class's fitted
mapping from the sensor's channels, and is determined from TouchSim itself and the simulated
sensor's response to the same stimuli. It does not carry a model's own adaptation or its
frequency tuning beyond its class's.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..encoding.encoder import encode_population
from ..params import EncoderParams
from ..recording import Trial
from ..reference.model import ReferenceModel
from ..settings import CLASSES
from ..simulator.eskin import SkinParams
from ..simulator.patch import probe_recording
from ..simulator.stimuli import RampHold, SineBurst
from ..stream import class_channels
from ..population.encoder import variant_params
from ..population.layout import PopulationPlan

GAIN_GRID = np.geomspace(1 / 16, 16, 65)  #: gains tried (the match interpolates between them)


def standard_set(skin: SkinParams) -> list:
    """Ramp-and-holds of 0.5, 1 and 1.5 mm at 20 mm/s (0.3 s hold) and 0.5 s bursts at 20, 60, 150
    and 300 Hz on the calibrated drive."""
    ramps = [RampHold(d, 20.0, 20.0, 0.3) for d in (0.5, 1.0, 1.5)]
    sines = [SineBurst.calibrated(f, skin, burst_s=0.5) for f in (20.0, 60.0, 150.0, 300.0)]
    return ramps + sines


def match_gains(params: EncoderParams, skin: SkinParams | None = None, seed: int = 0) -> dict[str, list[float]]:
    """Per class of ``params``, one gain per TouchSim model of the class (TouchSim's order)."""
    skin = skin or SkinParams()
    ref = ReferenceModel()
    classes = [c for c in CLASSES if c in params.classes]
    ref_counts = np.zeros(ref.n_models)
    ours = {c: np.zeros(GAIN_GRID.size) for c in classes}
    one = np.zeros((1, 2))
    for i, stim in enumerate(standard_set(skin)):
        rec = probe_recording(stim, (0.0, 0.0), one, skin=skin, seed=seed + i)
        resp = ref.simulate(rec.cmd_depth, probe_xy_mm=(0.0, 0.0), afferent_xy_mm=one, noisy=False)
        ref_counts += resp.counts()[0, 0]
        raw = rec.raw
        trial = Trial(st_t=raw.st_t, st=raw.st[:, 0], pvdf_t=raw.pvdf_t, pvdf=raw.pvdf[:, 0],
                      cmd_depth=rec.cmd_depth.astype(np.float32))
        channels = class_channels(trial, params, classes)
        for c in classes:
            ch = channels[c]
            trains = encode_population(ch.data[:, 0, :], ch.t0_s, [variant_params(params.classes[c], g) for g in GAIN_GRID])
            ours[c] += [t.size for t in trains]
    out = {}
    model_class = ref.constants.class_of_model
    for c in classes:
        n = ref_counts[model_class == CLASSES.index(c)]
        target = n / max(n.mean(), 1e-9)  # each model's count relative to its class's mean model
        at_one = ours[c][np.argmin(np.abs(np.log(GAIN_GRID)))]
        curve = np.maximum.accumulate(ours[c]) / max(at_one, 1.0)
        out[c] = [round(float(_invert(curve, r)), 4) for r in target]
    return out


def _invert(curve: np.ndarray, ratio: float) -> float:
    """The gain at which the (non-decreasing) count ratio ``curve`` over GAIN_GRID reaches ``ratio``
    (log-linear between grid points; the grid's ends beyond its range)."""
    if ratio <= curve[0]:
        return float(GAIN_GRID[0])
    if ratio >= curve[-1]:
        return float(GAIN_GRID[-1])
    k = int(np.searchsorted(curve, ratio, side="left"))
    lo, hi = curve[k - 1], curve[k]
    f = 0.0 if hi == lo else (ratio - lo) / (hi - lo)
    return float(np.exp(np.log(GAIN_GRID[k - 1]) + f * (np.log(GAIN_GRID[k]) - np.log(GAIN_GRID[k - 1]))))


def resolve_plan(params: EncoderParams, overrides: Sequence[str] = (), path: Path | None = None) -> PopulationPlan:
    """The plan of a file, or the default plan with overrides and variants matched for ``params``."""
    if path is not None:
        return PopulationPlan.from_dict(json.loads(Path(path).read_text()))
    fields = {}
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set takes FIELD=JSON, got {item!r}")
        try:
            fields[key] = json.loads(value)
        except json.JSONDecodeError as e:
            raise ValueError(f"--set {key}: not JSON ({e.msg})") from None
    if "variants" not in fields:
        fields["variants"] = match_gains(params)
    return PopulationPlan.from_dict({**asdict(PopulationPlan()), **fields})
