"""A fit's preprocessed trials: channels once per causal window, onset-aligned reference trains per
class, the contact-free baselines the PVDF stage is calibrated on, channel scales, the rig's lag,
and the fast simulation of many parameter sets on them (the product encoder's population)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numpy as np

from ..analysis.turning_points import turning_points, window_edges
from ..encoding.encoder import encode_population, class_filtered
from ..params import ClassParams, PreprocessParams
from ..preprocess.pipeline import preprocess_trial
from ..recording import Dataset, Trial
from ..settings import OUT_FS_HZ
from .objective import ReferenceSet


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

    def reference_set(self, cls: str, tau_s: float, max_refs: int, sine_weight: float = 1.0, segmented_count: bool = False,
                      vr_normalised: bool = False, sine_count_weight: float | None = None) -> ReferenceSet:
        """Reference trains of ``cls`` per condition. At most ``max_refs`` per condition: every
        trial keeps its first r repeats (all models of each), r >= 1 chosen to fit the cap. With
        ``segmented_count`` a ramp condition's count loss is split at its trials' turning-point
        windows (the commanded turning points are the same for every repeat); ``vr_normalised``:
        conditions are scored by the VR-normalised distance (:class:`ReferenceSet`). A sine condition
        weighs ``sine_weight`` ramp conditions, in the count terms ``sine_count_weight`` if given."""
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
        sine = [m[0].protocol == "sine" for m in members]
        weights = [sine_weight if s else 1.0 for s in sine]
        count_weights = None if sine_count_weight is None else [sine_count_weight if s else 1.0 for s in sine]
        edges = [m[0].window_edges_s for m in members] if segmented_count else None
        return ReferenceSet.build(groups, tau_s, names=self.conditions, weights=weights, segment_edges=edges, vr_normalised=vr_normalised,
                                  count_weights=count_weights)


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
    ds: Dataset, entries: Sequence[dict[str, Any]], margin_s: float = 0.02, loaded: dict[str, Trial] | None = None,
    channel: Literal["pvdf", "st"] = "pvdf",
) -> list[np.ndarray]:
    """Contact-free samples of ``channel`` (PVDF in V, SingleTact in N) before ``onset_s - margin_s``
    of the ramp/texture entries (the sine probe rests on the skin; its vibration-free baselines are
    used only without ramps)."""
    loaded = loaded or {}
    free = [e for e in entries if e["protocol"] in CONTACT_FREE_PROTOCOLS] or list(entries)
    out = []
    for e in free:
        tr = loaded[e["id"]] if e["id"] in loaded else ds.load(e)
        seg = np.asarray(getattr(tr, channel)[getattr(tr, channel + "_t") < float(e["onset_s"]) - margin_s], np.float64)
        if seg.size:
            out.append(seg)
    return out


def channel_scale(trials: Sequence[TrialData], lowpass_hz: float | None = None) -> np.ndarray:
    """Typical magnitude of each channel: 99th percentile of |x| over the trials, after a class
    low-pass at ``lowpass_hz`` when given (it shrinks the fast channels, dPVDF most)."""
    allc = np.concatenate([class_filtered(t.channels, lowpass_hz) for t in trials], axis=0)
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


def simulate(trials: Sequence[TrialData], params: Sequence[ClassParams], lag_s: float = 0.0) -> list[list[np.ndarray]]:
    """Onset-aligned spike trains ``[parameter set][trial]`` on the reference clock (stamps minus
    the rig's lag ``lag_s``): every set is one neuron of the product encoder's population
    (:func:`~touchreal.encoding.encoder.encode_population`)."""
    out: list[list[np.ndarray]] = [[] for _ in params]
    for tr in trials:
        for j, train in enumerate(encode_population(tr.channels, tr.k0 / OUT_FS_HZ, params)):
            out[j].append(train - lag_s - tr.onset_s)
    return out
