"""Early stopping of the texture MLP classifiers, validated on held-out training *trials*.

scikit-learn's own ``early_stopping=True`` validates on a random ``validation_fraction`` of the
*windows*: the windows of one trial (one build, one press depth, one speed) land on both sides,
so the validation accuracy measures recall of trials already trained on and training stops late,
on weights that fit the training trials' specifics. Here the validation windows are those of whole
training trials held aside:

1. :func:`trial_validation_split`: per texture label, a seeded shuffle of its training trials;
   the first ``round(VALIDATION_FRACTION * n)`` of them (at least one, at most ``n - 1``) validate.
   No trial has windows on both sides. A label with a single training trial only trains.
2. :func:`fit_mlp_by_trials`: the MLP trains on the other trials one epoch (one pass of Adam
   mini-batches over their shuffled windows) at a time (``partial_fit``); after each epoch its
   accuracy on the validation windows is measured; training stops after ``PATIENCE`` epochs in a
   row without an improvement of more than ``TOL`` over the best, or at ``MAX_EPOCHS``. The weights
   of the best epoch are kept (``REFIT`` false), or a fresh MLP trains on all the training trials
   for that many epochs (``REFIT`` true).

Deterministic from the seed: the split draws from ``numpy.random.default_rng(seed)``, the MLP's
initial weights and its per-epoch shuffles from one ``numpy.random.RandomState(seed)``. The result
is a plain fitted ``MLPClassifier`` (exported by skl2onnx as any other), with ``n_iter_`` the
epochs its weights were trained for, ``validation_scores_`` the validation accuracy per epoch and
``best_validation_score_`` as scikit-learn's early stopping sets them. When no label has two
training trials (nothing to validate on), it falls back to scikit-learn's stopping on the training
loss (``early_stopping=False``, ``n_iter_no_change=PATIENCE``, ``max_iter=MAX_EPOCHS``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from sklearn.neural_network import MLPClassifier

#: share of each texture's training trials held aside to validate on (about 75 of 500 trials)
VALIDATION_FRACTION = 0.15
#: epochs in a row without a validation improvement before training stops
PATIENCE = 15
#: at most this many epochs
MAX_EPOCHS = 300
#: an improvement is a validation accuracy above the best by more than this (scikit-learn's tol)
TOL = 1e-4
#: after stopping, refit on all the training trials for the best number of epochs (True) or keep
#: the best-validation weights of the model trained without the validation trials (False). True:
#: on texture-hard the kept models, which never see the held-out trials' builds, scored 0.8-2.7
#: points lower on the seen speeds and the unseen build stiff-film-slow-rig, and nowhere more
#: than 0.3 higher
REFIT = True


def trial_validation_split(target: np.ndarray, groups: np.ndarray, fraction: float = VALIDATION_FRACTION,
                           seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (train, validation) of windows ``target`` / ``groups`` (trial of each window), split by trial.

    Per label (a trial's label is its first window's), its trials in a seeded shuffle; the first
    ``clip(round(fraction * n), 1, n - 1)`` validate (none when ``n < 2``)."""
    target, groups = np.asarray(target), np.asarray(groups)
    trials, first = np.unique(groups, return_index=True)
    labels = target[first]
    rng = np.random.default_rng(seed)
    val_trials: list[np.ndarray] = []
    for lab in sorted(set(labels.tolist()), key=str):
        own = trials[labels == lab]
        if own.size < 2:
            continue
        k = int(np.clip(round(fraction * own.size), 1, own.size - 1))
        val_trials.append(rng.permutation(own)[:k])
    is_val = np.isin(groups, np.concatenate(val_trials)) if val_trials else np.zeros(groups.shape, bool)
    return np.flatnonzero(~is_val), np.flatnonzero(is_val)


@dataclass(frozen=True)
class Stopping:
    """How :func:`fit_mlp_by_trials` stopped."""

    best_epoch: int  #: epochs of the best validation accuracy (0: no validation, loss-based fallback)
    epochs_run: int  #: epochs trained before stopping
    scores: tuple[float, ...]  #: validation accuracy after each epoch
    n_train_trials: int
    n_val_trials: int


def fit_mlp_by_trials(x: np.ndarray, target: np.ndarray, groups: np.ndarray, seed: int = 0, *,
                      fraction: float = VALIDATION_FRACTION, patience: int = PATIENCE, max_epochs: int = MAX_EPOCHS,
                      tol: float = TOL, refit: bool = REFIT, **mlp: Any) -> tuple[MLPClassifier, Stopping]:
    """An ``MLPClassifier(**mlp)`` (Adam) fitted on ``x`` (already scaled) with early stopping on held-out trials."""
    for k in ("early_stopping", "max_iter", "n_iter_no_change", "random_state", "warm_start", "solver"):
        if k in mlp:
            raise ValueError(f"{k} is set by the trial-validated early stopping")
    target = np.asarray(target)
    tr, va = trial_validation_split(target, groups, fraction, seed)
    if va.size == 0:
        est = MLPClassifier(**mlp, early_stopping=False, max_iter=max_epochs, n_iter_no_change=patience, tol=tol,
                            random_state=seed).fit(x, target)
        return est, Stopping(0, int(est.n_iter_), (), int(np.unique(groups).size), 0)
    classes = np.unique(target)

    def fresh() -> MLPClassifier:
        # one RandomState for the whole fit: partial_fit re-reads random_state at each call, and an int
        # would give every epoch the same shuffle
        return MLPClassifier(**mlp, early_stopping=False, tol=tol, random_state=np.random.RandomState(seed))

    est = fresh()
    x_tr, y_tr, x_va, y_va = x[tr], target[tr], x[va], target[va]
    scores: list[float] = []
    best, best_epoch, best_w = -np.inf, 0, None
    for epoch in range(1, max_epochs + 1):
        est.partial_fit(x_tr, y_tr, classes=classes)
        s = float(np.mean(est.predict(x_va) == y_va))
        scores.append(s)
        if s > best + tol:
            best, best_epoch = s, epoch
            best_w = ([c.copy() for c in est.coefs_], [b.copy() for b in est.intercepts_])
        elif epoch - best_epoch >= patience:
            break
    stop = Stopping(best_epoch, len(scores), tuple(scores), int(np.unique(groups[tr]).size), int(np.unique(groups[va]).size))
    if refit:
        est = fresh()
        for _ in range(best_epoch):
            est.partial_fit(x, target, classes=classes)
    else:
        est.coefs_, est.intercepts_ = best_w
    est.n_iter_ = best_epoch
    est.validation_scores_ = list(scores)
    est.best_validation_score_ = best
    est.random_state = seed  # the parameter as given (the RandomState it drew from is spent)
    return est, stop
