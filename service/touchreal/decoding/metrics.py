"""Decoder metrics: the paper's Table 5 for force, accuracy with its spread for texture."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def oscillation(pred: np.ndarray, groups: np.ndarray) -> float:
    """Eq. 13: RMS of the second difference of consecutive predictions (N), within each trial."""
    d2 = [np.diff(pred[groups == g], 2) for g in np.unique(groups)]
    d2 = np.concatenate([d for d in d2 if d.size] or [np.zeros(0)])
    return float(np.sqrt(np.mean(d2**2))) if d2.size else float("nan")


def force_metrics(y: np.ndarray, pred: np.ndarray, groups: np.ndarray) -> dict[str, float | list[float]]:
    """RMSE, MAE (N), oscillation (eq. 13; also of the measured force, for scale), R^2, Pearson r
    over all windows, and the per-trial RMSE distribution (``trial_rmse``: one value per trial; its median and quartiles)."""
    y, pred = np.asarray(y, np.float64), np.asarray(pred, np.float64)
    err = pred - y
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    trial = [float(np.sqrt(np.mean(err[groups == g] ** 2))) for g in np.unique(groups)]
    q1, med, q3 = np.percentile(trial, [25, 50, 75]) if trial else (np.nan,) * 3
    return {
        "rmse": float(np.sqrt(np.mean(err**2))),
        "mae": float(np.mean(np.abs(err))),
        "oscillation": oscillation(pred, groups),
        "oscillation_measured": oscillation(y, groups),
        "r2": float(1.0 - np.sum(err**2) / ss_tot) if ss_tot > 0 else float("nan"),
        "pearson_r": float(np.corrcoef(y, pred)[0, 1]) if y.size > 1 and np.std(pred) > 0 else float("nan"),
        "n_windows": int(y.size),
        "n_trials": len(trial),
        "trial_rmse_median": float(med),
        "trial_rmse_q1": float(q1),
        "trial_rmse_q3": float(q3),
        "trial_rmse": [round(v, 5) for v in trial],
    }


def fold_of_trials(labels: Sequence[str], n_folds: int) -> np.ndarray:
    """Fold of each trial: trials of a label are dealt round-robin in the given order (stratified)."""
    seen: dict[str, int] = {}
    out = np.zeros(len(labels), int)
    for i, lab in enumerate(labels):
        out[i] = seen.get(lab, 0) % n_folds
        seen[lab] = seen.get(lab, 0) + 1
    return out


def texture_metrics(true: np.ndarray, pred: np.ndarray, groups: np.ndarray, trial_fold: np.ndarray) -> dict[str, float | list[float]]:
    """Window accuracy overall and per fold of trials (mean, std across folds)."""
    correct = np.asarray(true) == np.asarray(pred)
    fold = trial_fold[groups]
    per = [float(correct[fold == f].mean()) for f in np.unique(fold)]
    return {
        "acc": float(correct.mean()) if correct.size else float("nan"),
        "acc_fold_mean": float(np.mean(per)) if per else float("nan"),
        "acc_fold_std": float(np.std(per)) if per else float("nan"),
        "acc_folds": [round(v, 4) for v in per],
        "n_windows": int(correct.size),
    }
