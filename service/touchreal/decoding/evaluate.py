"""Run exported decoders through onnxruntime on a dataset's trials and compute their metrics.

Used by ``touchreal decoders evaluate`` and by ``train`` (held-out metrics into the metadata), so
a model's recorded metrics and a later evaluation come from one code path: ONNX, not scikit-learn.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..params import EncoderParams
from ..recording import Dataset
from .metrics import fold_of_trials, force_metrics, texture_metrics
from .model import DecoderModel, with_pvdf_window
from .plan import ModelSpec, spec_from_meta
from .train import windows
from .windows import FORCE_PROTOCOL, TEXTURE_PROTOCOL, EncodedTrial, encode, require_trials, split_entries

N_FOLDS = 5  #: folds of held-out trials for the accuracy spread


def protocol_of(task: str) -> str:
    return FORCE_PROTOCOL if task == "force" else TEXTURE_PROTOCOL


class TrialCache:
    """Encoded trials of one dataset, per (trial, PVDF-window override), encoded once."""

    def __init__(self, ds: Dataset, params: EncoderParams, progress: Callable[[], None] | None = None):
        self.ds, self.params, self.progress = ds, params, progress
        self.split_seed: int | None = None
        self._enc: dict[tuple[str, tuple], EncodedTrial] = {}

    def trials(self, spec: ModelSpec, split: str) -> list[EncodedTrial]:
        protocol = protocol_of(spec.task)
        require_trials(self.ds, protocol, f"{spec.task} decoding")
        entries, self.split_seed = split_entries(self.ds, self.params, protocol, split)
        params = with_pvdf_window(self.params, spec.pvdf_window_ms)
        out = []
        for e in entries:
            key = (e["id"], spec.pvdf_window_ms)
            if key not in self._enc:
                self._enc[key] = encode(e, self.ds.load(e), params)
                if self.progress is not None:
                    self.progress()
            out.append(self._enc[key])
        return out

    def n_to_encode(self, specs: Sequence[ModelSpec], split: str) -> int:
        """How many trial encodings ``specs`` need (for a progress bar)."""
        keys = set()
        for s in specs:
            protocol = protocol_of(s.task)
            if self.ds.entries(protocol):
                keys |= {(e["id"], s.pvdf_window_ms) for e in split_entries(self.ds, self.params, protocol, split)[0]}
        return len(keys - set(self._enc))


def evaluate_model(model: DecoderModel, trials: Sequence[EncodedTrial], threads: int = 1) -> dict[str, Any]:
    """Metrics of one model on ``trials`` (its windows), through onnxruntime."""
    spec = spec_from_meta(model.meta)
    counts, target, groups, _, speed = windows(spec, trials)
    if counts.shape[0] == 0:
        return {"n_windows": 0}
    out = model.run_windows(model.session(threads), counts, groups, speed)
    if spec.task == "force":
        return force_metrics(target, out[:, 0], groups)
    labels = np.asarray(model.meta["labels"], dtype=object)
    pred = labels[np.argmax(out, axis=1)]
    metrics = texture_metrics(target, pred, groups, fold_of_trials([t.label for t in trials], N_FOLDS))
    if speed is not None:  # a scanning model: accuracy per trial speed (median of its windows', mm/s to 0.1)
        trial_v = {g: round(float(np.median(speed[groups == g, 0])), 1) for g in np.unique(groups)}
        v = np.array([trial_v[g] for g in groups])
        metrics["acc_by_speed_mm_s"] = {f"{s:g}": float(np.mean(target[v == s] == pred[v == s])) for s in np.unique(v)}
    _, n = np.unique(target, return_counts=True)
    return metrics | {"chance": 1.0 / len(labels), "chance_majority": float(n.max() / n.sum()), "n_trials": len(trials),
                      "n_trials_without_window": len(trials) - int(np.unique(groups).size)}


def flat_metrics(spec: ModelSpec, metrics: dict[str, Any]) -> dict[str, Any]:
    """One model's metrics under their METRICS.json keys (texture adds the chance level 1/labels)."""
    if metrics.get("n_windows", 0) == 0:
        return {f"{spec.name}.n_windows": 0}
    flat = spec.metric_keys(metrics)
    if spec.task == "texture":
        flat["texture.chance"] = metrics["chance"]
    return flat


def evaluate_models(models: Sequence[DecoderModel], cache: TrialCache, split: str, threads: int = 1,
                    done: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Flat METRICS.json dict of every model (keys from :meth:`ModelSpec.metric_keys`)."""
    flat: dict[str, Any] = {}
    for m in models:
        spec = spec_from_meta(m.meta)
        flat.update(flat_metrics(spec, evaluate_model(m, cache.trials(spec, split), threads)))
        if done is not None:
            done(spec.name)
    return flat
