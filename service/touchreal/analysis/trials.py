"""Held-out selection and the encoding of evaluation trials: each trial preprocessed at its
classes' causal windows and encoded with the product's own population code; trains on the
reference clock, relative to the commanded onset (s)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..encoding.encoder import encode_population
from ..params import EncoderParams
from ..preprocess.pipeline import preprocess_trial
from ..recording import Dataset
from ..splits import FIT_PROTOCOLS, fitted_on_every_trial, params_split_seed, split_repeats


@dataclass
class EvalTrial:
    entry: dict[str, Any]
    onset: float
    tr: dict[str, np.ndarray]  # class -> TouchReal train (onset-aligned)
    ts: dict[str, list[np.ndarray]] = field(default_factory=dict)  # class -> TouchSim trains (onset-aligned)
    ts_repeats: dict[str, int] = field(default_factory=dict)
    channels: np.ndarray | None = None  # (T, 4) when kept
    k0: int = 0


def _iter(items, progress: bool, desc: str):
    if progress:
        from tqdm import tqdm

        return tqdm(items, desc=desc, unit="trial", dynamic_ncols=True)
    return items


def run_trials(
    ds: Dataset, entries: Sequence[dict[str, Any]], params: EncoderParams, classes: Sequence[str], keep_channels: bool | set[str] = False,
    window_ms: float | None = None, progress: bool = False, desc: str = "encode",
) -> list[EvalTrial]:
    """Preprocess + encode every entry: each class at its own causal PVDF window (``window_ms``
    overrides every class's), one population per window and trial; spike trains on the reference
    clock (:meth:`EncoderParams.reference_times`), relative to the commanded onset.

    ``keep_channels``: keep the 5 kHz channels of every trial (True) or of the trial ids given; they
    are the channels of the preprocessing window (``params.preprocess.window_ms``, or ``window_ms``)."""
    groups: dict[float, list[str]] = {}
    for c in classes:
        groups.setdefault(float(window_ms if window_ms is not None else params.window_ms(c)), []).append(c)
    kept_w = float(window_ms if window_ms is not None else params.preprocess.window_ms)
    out = []
    for e in _iter(entries, progress, desc):
        trial = ds.load(e)
        onset = float(e["onset_s"])
        trains: dict[str, np.ndarray] = {}
        ch_kept = None
        for w in sorted(set(groups) | ({kept_w} if keep_channels else set())):
            ch = preprocess_trial(trial, params.preprocess.model_copy(update={"window_ms": w}))
            x = np.ascontiguousarray(ch.data[:, 0, :])
            if w == kept_w:
                ch_kept = (x, int(ch.k0))
            on_w = groups.get(w, [])
            if on_w:
                for c, t in zip(on_w, encode_population(x, ch.t0_s, [params.classes[c] for c in on_w])):
                    trains[c] = params.reference_times(t) - onset
        et = EvalTrial(e, onset, {c: trains[c] for c in classes})
        for c in classes:
            if c in trial.reference:
                r = trial.reference[c]
                et.ts[c] = [np.sort(np.asarray(t, np.float64)) - onset for t in r.trains()]
                et.ts_repeats[c] = r.repeats
        if ch_kept is not None and (keep_channels is True or (isinstance(keep_channels, set) and e["id"] in keep_channels)):
            et.channels, et.k0 = ch_kept
        out.append(et)
    return out


def by_condition(trials: Sequence[EvalTrial]) -> dict[str, list[EvalTrial]]:
    out: dict[str, list[EvalTrial]] = {}
    for t in trials:
        out.setdefault(t.entry["condition"], []).append(t)
    return out


def select_held_out(ds: Dataset, params: EncoderParams, mode: str = "auto") -> tuple[list[dict[str, Any]], list[dict[str, Any]], str]:
    """(evaluated ramp+sine entries, all ramp+sine entries, description).

    ``auto``: the fit's held-out trials (all trials for parameters fitted elsewhere); ``all``: every
    trial; ``train``: the fit's training half, for choosing fit settings without looking at the
    held-out trials."""
    if mode not in ("auto", "all", "train"):
        raise ValueError("split must be 'auto', 'all' or 'train'")
    entries = [e for e in ds.entries() if e["protocol"] in FIT_PROTOCOLS and e.get("reference")]
    if mode != "all" and fitted_on_every_trial(params, ds):
        return entries, entries, (f"all {len(entries)} ramp/sine trials: the fit TRAINED on every one (no held-out part; "
                                  "not a held-out result - evaluate a separate recording for that)")
    seed = params_split_seed(params, ds) if mode != "all" else None
    if seed is None:
        if mode == "train":
            raise ValueError("--split train needs parameters fitted on this dataset by `touchreal fit` (the split seed is in their provenance)")
        why = "requested" if mode == "all" else "the parameters were not fitted on this dataset by `touchreal fit`"
        return entries, entries, f"all {len(entries)} ramp/sine trials ({why})"
    train, held = split_repeats(entries, seed)
    if mode == "train":
        return train, entries, f"{len(train)} TRAINING ramp/sine trials of {len(entries)} (split seed {seed}; not a held-out result)"
    return held, entries, f"{len(held)} held-out ramp/sine trials of {len(entries)} (split seed {seed}, as recorded by the fit)"
