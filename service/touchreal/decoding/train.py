"""Training: windows of the training trials -> scikit-learn pipeline -> ONNX with metadata.

Force: ``StandardScaler`` + ``MLPRegressor`` (64, 32 ReLU units, early stopping) on the flattened
counts (and, stateful, their filtered counts carried across steps). Texture ``spectral`` and
``spatial``: ``StandardScaler`` + ``MLPClassifier`` (128 ReLU units, early stopping validated on held-out
training trials, :mod:`touchreal.decoding.early_stopping`). Other texture sets:
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
from typing import Any, NamedTuple

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
from .early_stopping import PATIENCE, REFIT, VALIDATION_FRACTION, fit_mlp_by_trials
from .export import INPUT_NAME, REGRESSION_OUTPUT, to_onnx
from .features import (BANDS_HZ, INTERVAL_MAX_RATE_HZ, INTERVAL_MM, INTERVAL_ORDERS, SMOOTH_SIGMA_MS, SPATIAL_CYCLES_PER_MM,
                       SPECTRUM_HZ, SPEED_INPUT, FeatureSpec)
from .model import SCHEMA, SCHEMA_VERSION, params_hash, with_pvdf_window
from .plan import ModelSpec
from .state import STATE_INPUT, STATE_OUTPUT, ExpFilter
from .windows import SCAN_STEADY, TEXTURE_SILENCE_US, EncodedTrial, force_windows, scan_windows, texture_windows

SVC_C = 10.0
CALIBRATION_FOLDS = 3


def feature_spec(spec: ModelSpec) -> FeatureSpec:
    nb = F.n_bins(round(spec.window_ms * 1000), round(spec.bin_ms * 1000))
    state = ExpFilter(spec.state_taus_ms, spec.step_ms, nb, len(spec.classes)) if spec.state_taus_ms else None
    return FeatureSpec(spec.features, nb, len(spec.classes), spec.bin_ms, spec.window_ms, state)


class Windows(NamedTuple):
    """Decoding windows of recorded trials for one model."""

    counts: np.ndarray  #: (n, n_bins, n_classes) float32
    target: np.ndarray  #: force (N) or label strings (object)
    groups: np.ndarray  #: trial index of each window
    steps: np.ndarray  #: step time T (us)
    speed: np.ndarray | None  #: (n, 1) float32 scanning speed (mm/s) for a model that reads it, else None


def windows(spec: ModelSpec, trials: Sequence[EncodedTrial]) -> Windows:
    """The windows of ``trials`` for ``spec``. A stateful model's windows are every step of each
    trial from the recording's start; a ``spatial`` texture model's the scanning windows."""
    w_us, bin_us = round(spec.window_ms * 1000), round(spec.bin_ms * 1000)
    if spec.task == "force":
        return Windows(*force_windows(trials, spec.classes, w_us, step_us=round(spec.step_ms * 1000),
                                      from_start=bool(spec.state_taus_ms)), None)
    if spec.features == "spatial":
        x, labels, g, t, v = scan_windows(trials, w_us, bin_us, spec.classes)
        return Windows(x, np.asarray(labels, dtype=object), g, t, v.astype(np.float32).reshape(-1, 1))
    x, labels, g, t = texture_windows(trials, w_us, bin_us=bin_us, classes=spec.classes)
    return Windows(x, np.asarray(labels, dtype=object), g, t, None)


def fit_pipeline(spec: ModelSpec, feats: np.ndarray, target: np.ndarray, groups: np.ndarray, seed: int) -> Pipeline:
    """Fit the scikit-learn pipeline of ``spec`` on a feature matrix."""
    if spec.task == "force":
        mlp = MLPRegressor(hidden_layer_sizes=(64, 32), alpha=1e-3, max_iter=400, early_stopping=True,
                           n_iter_no_change=20, random_state=seed)
        return make_pipeline(StandardScaler(), mlp).fit(feats, target)
    if spec.features in ("spectral", "spatial"):
        # early stopping validated on held-out training trials (early_stopping.py), not on random windows
        scaler = StandardScaler().fit(feats)
        mlp, _ = fit_mlp_by_trials(scaler.transform(feats), target, groups, seed, hidden_layer_sizes=(128,), alpha=1e-3)
        return make_pipeline(scaler, mlp)
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
                        f"({spec.features} features), {spec.window_ms:g} ms window "
                        + ("with the scanning speed (mm/s) as a second input" if fs.needs_speed else "anchored at the first PC spike")),
        "input": {"name": INPUT_NAME, "shape": [None, fs.n_bins, fs.n_classes], "dtype": "float32",
                  "layout": "(batch = taxels, bins oldest -> newest, classes in 'classes' order)"},
        "context": {"input": SPEED_INPUT, "shape": [None, 1], "dtype": "float32", "unit": "mm/s",
                    "rule": "the scanning speed of the surface under the taxels over the window [T - window, T): one row "
                            "(1, 1) for every taxel or one per taxel (batch, 1); > 0; a window without steady scanning "
                            "has no texture output (NaN)"} if fs.needs_speed else None,
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
        "alignment": None if spec.task == "force" or fs.needs_speed else {
            "rule": F.ALIGN_RULE, "class": "PC", "silence_ms": TEXTURE_SILENCE_US / 1000,
            "doc": "touchreal_client.features.anchors / anchored_end / StreamBinner: window ends on anchor + k * bin "
                   "<= step, output once end - anchor >= window"},
        "features": {"set": spec.features, "order": fs.names(), "smoothing_sigma_ms": SMOOTH_SIGMA_MS,
                     "bands_hz": [list(b) for b in BANDS_HZ], "spectrum_hz": list(SPECTRUM_HZ),
                     "spatial_cycles_per_mm": list(SPATIAL_CYCLES_PER_MM) if fs.needs_speed else None,
                     "intervals_mm": list(INTERVAL_MM) if fs.needs_speed else None,
                     "interval_orders": list(INTERVAL_ORDERS) if fs.needs_speed else None,
                     "interval_max_rate_hz": INTERVAL_MAX_RATE_HZ if fs.needs_speed else None,
                     "scan_steady": SCAN_STEADY if fs.needs_speed else None, "in_graph": True},
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
    if isinstance(est, MLPClassifier) and not est.early_stopping:  # fit_mlp_by_trials
        head = f"StandardScaler + MLPClassifier(hidden={est.hidden_layer_sizes}, relu, alpha={est.alpha}, iterations={est.n_iter_}"
        if getattr(est, "best_validation_score_", None) is None:
            return head + ": stopped on the training loss, no texture had two training trials to hold one out)"
        return (head + f": the best epoch on {VALIDATION_FRACTION:g} of the training trials held out (patience {PATIENCE}, "
                f"validation accuracy {est.best_validation_score_:.4f}){', then refit on all of them' if REFIT else ''})")
    if isinstance(est, (MLPRegressor, MLPClassifier)):
        return f"StandardScaler + {type(est).__name__}(hidden={est.hidden_layer_sizes}, relu, alpha={est.alpha}, iterations={est.n_iter_})"
    svc = est.estimator
    return f"StandardScaler + CalibratedClassifierCV(SVC(rbf, C={svc.C}, gamma=scale), sigmoid, ensemble=False, trial folds)"


def train_model(
    spec: ModelSpec, trials: Sequence[EncodedTrial], params: EncoderParams, training: dict[str, Any], seed: int = 0
) -> tuple[onnx.ModelProto, dict[str, Any], Pipeline, FeatureSpec]:
    """Fit ``spec`` on ``trials`` and export it (metrics still empty)."""
    fs = feature_spec(spec)
    w = windows(spec, trials)
    if w.counts.shape[0] == 0:
        raise ValueError(f"{spec.name}: the training trials give no decoding window"
                         + (" (scanning windows need each trial's cmd_x, or params.speed_mm_s with events slide_start_s and "
                            "slide_end_s)" if fs.needs_speed else ""))
    pipe = fit_pipeline(spec, fs.transform(w.counts, w.groups, w.speed), w.target, w.groups, seed)
    meta = metadata(spec, fs, pipe, params, training | {"windows": int(w.counts.shape[0]), "trials": len(trials)})
    return to_onnx(pipe, fs, meta), meta, pipe, fs
