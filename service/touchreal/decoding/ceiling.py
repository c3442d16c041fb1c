"""The raw-PVDF ceiling of the scanning texture task (``touchreal decoders ceiling``).

What the film itself carries, measured on the very windows, trials and split the spike decoder
``texture_spatial`` uses: the PVDF (2 kHz, V) averaged into the model's 1 ms bins, the window's
mean removed, the magnitude of its Hann-tapered Fourier transform at the same spatial frequencies
``k`` (temporal frequency ``k * v``, :meth:`FeatureSpec.spatial_grid`) divided by the window's
tapered RMS, in log, plus the log RMS; classifier: the spike decoder's (``StandardScaler`` +
``MLPClassifier``). Offline only (numpy and scikit-learn), not a product decoder.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from touchreal_client import features as F

from ..recording import Trial
from .features import FeatureSpec
from .metrics import fold_of_trials, texture_metrics
from .plan import ModelSpec
from .train import feature_spec, fit_pipeline, windows
from .windows import EncodedTrial, to_us

FLOOR = 1e-6  #: added before the log (relative magnitude)


def pvdf_bins(trial: Trial, ends_us: np.ndarray, window_us: int, bin_us: int) -> np.ndarray:
    """Mean PVDF (V) per bin of the windows ending at ``ends_us``: ``(len(ends), n_bins)`` float64."""
    t = to_us(trial.pvdf_t)
    csum = np.concatenate(([0.0], np.cumsum(np.asarray(trial.pvdf, np.float64))))
    idx = np.searchsorted(t, F.bin_edges(ends_us, window_us, bin_us), side="left")
    n = np.diff(idx, axis=1)
    return np.diff(csum[idx], axis=1) / np.maximum(n, 1)


def film_features(x: np.ndarray, speed: np.ndarray, fs: FeatureSpec) -> np.ndarray:
    """Log relative spectrum of binned PVDF windows ``(n, n_bins)`` on the spatial axis, then log RMS."""
    _, tk, taper = fs.spatial_grid()
    x = (x - x.mean(axis=1, keepdims=True)) * taper
    norm = np.sqrt(np.sum(x * x, axis=1, keepdims=True)) + 1e-12
    phase = 2 * np.pi * speed.reshape(-1, 1, 1) * tk[None]
    re = np.einsum("nb,nbk->nk", x, np.cos(phase))
    im = np.einsum("nb,nbk->nk", x, np.sin(phase))
    mag = np.sqrt(re * re + im * im) / norm
    return np.concatenate([np.log(mag + FLOOR), np.log(norm / np.sqrt(x.shape[1]))], axis=1).astype(np.float32)


def features_of(spec: ModelSpec, trials: Sequence[EncodedTrial], raw: Sequence[Trial]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(film features, labels, trial index) of the scanning windows of ``trials`` (``raw``: their recordings)."""
    fs = feature_spec(spec)
    w = windows(spec, trials)
    w_us, bin_us = round(spec.window_ms * 1000), round(spec.bin_ms * 1000)
    feats = np.zeros((w.counts.shape[0], len(fs.spatial_grid()[0]) + 1), np.float32)
    for i, tr in enumerate(raw):
        rows = np.flatnonzero(w.groups == i)
        if rows.size:
            feats[rows] = film_features(pvdf_bins(tr, w.steps[rows], w_us, bin_us), w.speed[rows], fs)
    return feats, w.target, w.groups


def ceiling(spec: ModelSpec, train: Sequence[EncodedTrial], train_raw: Sequence[Trial], test: Sequence[EncodedTrial],
            test_raw: Sequence[Trial], seed: int = 0, n_folds: int = 5) -> dict:
    """Held-out texture metrics of the film classifier for the windows of ``spec`` (a spatial model's)."""
    x, y, g = features_of(spec, train, train_raw)
    if x.shape[0] == 0:
        raise ValueError("the training trials give no scanning window")
    pipe = fit_pipeline(spec, x, y, g, seed)
    hx, hy, hg = features_of(spec, test, test_raw)
    if hx.shape[0] == 0:
        raise ValueError("the test trials give no scanning window")
    pred = pipe.predict(hx)
    return texture_metrics(hy, pred, hg, fold_of_trials([t.label for t in test], n_folds)) | {"n_trials": len(test)}
