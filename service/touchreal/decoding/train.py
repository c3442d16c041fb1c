"""Training: windows of the training trials -> scikit-learn pipeline -> ONNX with metadata.

Force: ``StandardScaler`` + ``MLPRegressor`` (64, 32 ReLU units, early stopping) on the flattened
counts (and, stateful, their filtered counts carried across steps). Texture ``spectral``:
``StandardScaler`` + ``MLPClassifier`` (128 ReLU units, early stopping). Other texture sets:
``StandardScaler`` + an RBF ``SVC`` calibrated to probabilities with
``CalibratedClassifierCV(ensemble=False)`` on folds of whole trials (scikit-learn's own
``SVC(probability=True)`` is deprecated and calibrates on folds of windows, which would mix a
trial's windows across its internal folds). Every model is then evaluated by
:mod:`touchreal.decoding.evaluate` through onnxruntime on the held-out trials and its metrics go
into its metadata.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np
import onnx
import skl2onnx
import sklearn
from sklearn.calibration import CalibratedClassifierCV
from sklearn.model_selection import StratifiedGroupKFold
from sklearn.neural_network import MLPClassifier, MLPRegressor
from sklearn.pipeline import Pipeline, make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC
from touchreal_client import features as F

from .. import __version__
from ..params import EncoderParams
from .export import INPUT_NAME, REGRESSION_OUTPUT, to_onnx
from .features import BANDS_HZ, SMOOTH_SIGMA_MS, SPECTRUM_HZ, FeatureSpec
from .model import SCHEMA, SCHEMA_VERSION, params_hash, with_pvdf_window
from .plan import ModelSpec
from .state import STATE_INPUT, STATE_OUTPUT, ExpFilter
from .windows import TEXTURE_SILENCE_US, EncodedTrial, force_windows, texture_windows

SVC_C = 10.0
CALIBRATION_FOLDS = 3


def feature_spec(spec: ModelSpec) -> FeatureSpec:
    nb = F.n_bins(round(spec.window_ms * 1000), round(spec.bin_ms * 1000))
    state = ExpFilter(spec.state_taus_ms, spec.step_ms, nb, len(spec.classes)) if spec.state_taus_ms else None
    return FeatureSpec(spec.features, nb, len(spec.classes), spec.bin_ms, spec.window_ms, state)


def windows(spec: ModelSpec, trials: Sequence[EncodedTrial]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(counts, target, trial index, step us) of ``trials`` for ``spec``: force (N) or label strings.
    A stateful model's windows are every step of each trial from the recording's start."""
    w_us = round(spec.window_ms * 1000)
    if spec.task == "force":
        return force_windows(trials, spec.classes, w_us, step_us=round(spec.step_ms * 1000), from_start=bool(spec.state_taus_ms))
    x, labels, g, t = texture_windows(trials, w_us, bin_us=round(spec.bin_ms * 1000), classes=spec.classes)
    return x, np.asarray(labels, dtype=object), g, t


def fit_pipeline(spec: ModelSpec, feats: np.ndarray, target: np.ndarray, groups: np.ndarray, seed: int) -> Pipeline:
    """Fit the scikit-learn pipeline of ``spec`` on a feature matrix."""
    if spec.task == "force":
        mlp = MLPRegressor(hidden_layer_sizes=(64, 32), alpha=1e-3, max_iter=400, early_stopping=True,
                           n_iter_no_change=20, random_state=seed)
        return make_pipeline(StandardScaler(), mlp).fit(feats, target)
    if spec.features == "spectral":
        mlp = MLPClassifier(hidden_layer_sizes=(128,), alpha=1e-3, max_iter=300, early_stopping=True,
                            n_iter_no_change=15, random_state=seed)
        return make_pipeline(StandardScaler(), mlp).fit(feats, target)
    _, first = np.unique(groups, return_index=True)  # one row per trial
    names, per_label = np.unique(target[first], return_counts=True)
    if names.size < 2 or per_label.min() < 2:
        raise ValueError("texture training needs at least two textures and two training trials of each "
                         f"(trials per texture in the training split: {dict(zip(names.tolist(), per_label.tolist()))})")
    cv = StratifiedGroupKFold(n_splits=min(CALIBRATION_FOLDS, int(per_label.min())))
    folds = list(cv.split(feats, target, groups))
    svc = CalibratedClassifierCV(SVC(C=SVC_C, gamma="scale"), ensemble=False, cv=folds)
    return make_pipeline(StandardScaler(), svc).fit(feats, target)


def metadata(spec: ModelSpec, fs: FeatureSpec, pipe: Pipeline, params: EncoderParams, training: dict[str, Any]) -> dict[str, Any]:
    """The model's metadata (format in docs/decoders.md); ``metrics`` is filled after evaluation."""
    labels = [str(c) for c in pipe.classes_] if spec.task == "texture" else None
    used = with_pvdf_window(params, spec.pvdf_window_ms)
    meta: dict[str, Any] = {
        "schema": SCHEMA,
        "version": SCHEMA_VERSION,
        "name": spec.name,
        "task": spec.task,
        "description": (f"force (N) from {'+'.join(spec.classes)} counts, {spec.window_ms:g} ms causal window"
                        + (f" and step, with their exponential filters ({', '.join(f'{t:g}' for t in spec.state_taus_ms)} ms) "
                           "carried across steps in 'state'" if spec.state_taus_ms else "")
                        if spec.task == "force" else f"texture from {'+'.join(spec.classes)} counts in {spec.bin_ms:g} ms bins "
                        f"({spec.features} features), {spec.window_ms:g} ms window anchored at the first PC spike"),
        "input": {"name": INPUT_NAME, "shape": [None, fs.n_bins, fs.n_classes], "dtype": "float32",
                  "layout": "(batch = taxels, bins oldest -> newest, classes in 'classes' order)"},
        "outputs": ([REGRESSION_OUTPUT] + ([STATE_OUTPUT] if fs.state else [])) if spec.task == "force" else ["probabilities", "label"],
        "output_names": [REGRESSION_OUTPUT] if spec.task == "force" else labels,
        "labels": labels,
        "classes": list(spec.classes),
        "bin_ms": spec.bin_ms,
        "window_ms": spec.window_ms,
        "step_ms": spec.step_ms,
        "state": None if fs.state is None else {
            "input": STATE_INPUT, "output": STATE_OUTPUT, "size": fs.state.size, "initial": 0.0,
            "taus_ms": list(spec.state_taus_ms), "order": fs.state.names(spec.classes),
            "rule": "state_out = exp(-step_ms / tau) * state + the window's spike count of the class; feed state_out "
                    "back as state at the next step, zeros (batch, size) at the first; one row per taxel"},
        "binning": "touchreal_client.features.window_counts: ceil(window/bin) bins counted back from the window end, "
                   "oldest first, the oldest bin truncated; a bin [a, b) counts a <= t < b (sensor clock, us)",
        "alignment": None if spec.task == "force" else {
            "rule": F.ALIGN_RULE, "class": "PC", "silence_ms": TEXTURE_SILENCE_US / 1000,
            "doc": "touchreal_client.features.anchors / anchored_end / StreamBinner: window ends on anchor + k * bin "
                   "<= step, output once end - anchor >= window"},
        "features": {"set": spec.features, "order": fs.names(), "smoothing_sigma_ms": SMOOTH_SIGMA_MS,
                     "bands_hz": [list(b) for b in BANDS_HZ], "spectrum_hz": list(SPECTRUM_HZ), "in_graph": True},
        "estimator": _describe(pipe),
        "params": {"sha256": params_hash(used), "pvdf_window_ms": spec.pvdf_window_ms,
                   "source": str(params.provenance.get("source") or params.provenance.get("dataset") or "unknown"),
                   "provenance": {k: params.provenance[k] for k in ("fitted_by", "dataset", "split_seed", "code") if k in params.provenance}},
        "training": training | {"folder": spec.folder},
        "metrics": {},
        "versions": {"touchreal": __version__, "scikit-learn": sklearn.__version__, "skl2onnx": skl2onnx.__version__, "onnx": onnx.__version__},
    }
    return json.loads(json.dumps(meta))  # plain JSON types only


def _describe(pipe: Pipeline) -> str:
    est = pipe.steps[-1][1]
    if isinstance(est, (MLPRegressor, MLPClassifier)):
        return f"StandardScaler + {type(est).__name__}(hidden={est.hidden_layer_sizes}, relu, alpha={est.alpha}, iterations={est.n_iter_})"
    svc = est.estimator
    return f"StandardScaler + CalibratedClassifierCV(SVC(rbf, C={svc.C}, gamma=scale), sigmoid, ensemble=False, trial folds)"


def train_model(
    spec: ModelSpec, trials: Sequence[EncodedTrial], params: EncoderParams, training: dict[str, Any], seed: int = 0
) -> tuple[onnx.ModelProto, dict[str, Any], Pipeline, FeatureSpec]:
    """Fit ``spec`` on ``trials`` and export it (metrics still empty)."""
    fs = feature_spec(spec)
    counts, target, groups, _ = windows(spec, trials)
    if counts.shape[0] == 0:
        raise ValueError(f"{spec.name}: the training trials give no decoding window")
    pipe = fit_pipeline(spec, fs.transform(counts, groups), target, groups, seed)
    meta = metadata(spec, fs, pipe, params, training | {"windows": int(counts.shape[0]), "trials": len(trials)})
    return to_onnx(pipe, fs, meta), meta, pipe, fs
