"""Early stopping of the texture MLPs on held-out training trials (touchreal.decoding.early_stopping)."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.neural_network import MLPClassifier

from touchreal.decoding.early_stopping import PATIENCE, VALIDATION_FRACTION, fit_mlp_by_trials, trial_validation_split
from touchreal.decoding.plan import ModelSpec
from touchreal.decoding.train import _describe, fit_pipeline


def _trials(n_labels: int = 4, per_label: int = 10, per_trial: int = 25, seed: int = 0):
    """Windows of trials: a label's mean, a per-trial offset (its 'build') and noise; trial ids shuffled."""
    rng = np.random.default_rng(seed)
    centers = rng.normal(0, 1.0, (n_labels, 12))
    xs, ys, gs = [], [], []
    ids = rng.permutation(n_labels * per_label) + 100  # trial ids need not be 0..n-1 nor ordered by label
    for t, tid in enumerate(ids):
        lab = t % n_labels
        offset = rng.normal(0, 0.8, 12)
        xs.append(centers[lab] + offset + rng.normal(0, 1.0, (per_trial, 12)))
        ys += [f"comb_{lab}"] * per_trial
        gs += [int(tid)] * per_trial
    return np.concatenate(xs).astype(np.float32), np.asarray(ys, object), np.asarray(gs)


def test_validation_split_is_by_trial_and_stratified():
    x, y, g = _trials(n_labels=5, per_label=20)
    tr, va = trial_validation_split(y, g, VALIDATION_FRACTION, seed=3)
    assert tr.size + va.size == y.size and np.intersect1d(tr, va).size == 0
    assert np.intersect1d(np.unique(g[tr]), np.unique(g[va])).size == 0  # no trial on both sides
    for lab in np.unique(y):  # per label round(0.15 * 20) = 3 trials validate, the 17 others train
        assert np.unique(g[va][y[va] == lab]).size == 3
        assert np.unique(g[tr][y[tr] == lab]).size == 17
    same = trial_validation_split(y, g, VALIDATION_FRACTION, seed=3)
    np.testing.assert_array_equal(same[1], va)  # deterministic from the seed
    other = trial_validation_split(y, g, VALIDATION_FRACTION, seed=4)
    assert not np.array_equal(other[1], va)


def test_split_keeps_a_training_trial_per_label_and_skips_single_trials():
    y = np.array(["a"] * 4 + ["b"] * 6 + ["c"] * 2, object)
    g = np.array([0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5])  # a: 2 trials, b: 3 trials, c: 1 trial
    tr, va = trial_validation_split(y, g, 0.5, seed=0)
    assert len(set(g[va]) & {0, 1}) == 1  # a: round(0.5 * 2) = 1 of its 2 trials validates
    assert len(set(g[va]) & {2, 3, 4}) == 2  # b: round(0.5 * 3) = 2 of 3, one left to train on
    assert 5 not in set(g[va])  # c: a single trial only trains
    assert np.intersect1d(np.unique(g[tr]), np.unique(g[va])).size == 0
    assert trial_validation_split(y, g, 0.99, seed=0)[0].size == 6  # at most n - 1 per label validate


def test_stopped_model_is_the_best_validation_one():
    x, y, g = _trials()
    est, stop = fit_mlp_by_trials(x, y, g, seed=1, hidden_layer_sizes=(16,), alpha=1e-3, refit=False)
    assert type(est) is MLPClassifier and not est.early_stopping
    scores = np.asarray(stop.scores)
    assert stop.best_epoch == int(np.argmax(scores)) + 1 and est.n_iter_ == stop.best_epoch
    assert stop.epochs_run == min(stop.best_epoch + PATIENCE, 300)  # stopped after PATIENCE epochs without improvement
    _, va = trial_validation_split(y, g, VALIDATION_FRACTION, seed=1)
    assert np.mean(est.predict(x[va]) == y[va]) == pytest.approx(scores.max()) == est.best_validation_score_
    assert stop.n_val_trials == 4 * round(VALIDATION_FRACTION * 10) and stop.n_train_trials == 40 - stop.n_val_trials
    assert "the best epoch on 0.15 of the training trials held out" in _describe(fit_pipeline(
        ModelSpec("t", "texture", ("PC",), 200.0, "spatial"), x, y, g, seed=1))


def test_deterministic_from_the_seed():
    x, y, g = _trials()
    a, sa = fit_mlp_by_trials(x, y, g, seed=2, hidden_layer_sizes=(16,), alpha=1e-3)
    b, sb = fit_mlp_by_trials(x, y, g, seed=2, hidden_layer_sizes=(16,), alpha=1e-3)
    assert sa == sb and a.random_state == 2
    for ca, cb in zip(a.coefs_ + a.intercepts_, b.coefs_ + b.intercepts_):
        np.testing.assert_array_equal(ca, cb)
    c, _ = fit_mlp_by_trials(x, y, g, seed=5, hidden_layer_sizes=(16,), alpha=1e-3)
    assert not np.array_equal(a.coefs_[0], c.coefs_[0])


def test_refit_trains_on_every_trial_for_the_best_epochs():
    x, y, g = _trials()
    est, stop = fit_mlp_by_trials(x, y, g, seed=1, hidden_layer_sizes=(16,), alpha=1e-3, refit=True)
    assert est.n_iter_ == stop.best_epoch == len(est.loss_curve_)  # a fresh model, best_epoch passes
    assert est.t_ == stop.best_epoch * y.size  # over all the windows, validation trials included


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_no_label_with_two_trials_falls_back_to_the_training_loss():
    x, y, g = _trials(n_labels=3, per_label=1)
    est, stop = fit_mlp_by_trials(x, y, g, seed=0, hidden_layer_sizes=(8,), alpha=1e-3)
    assert stop.best_epoch == 0 and stop.n_val_trials == 0 and est.n_iter_ == stop.epochs_run > 0
    assert est.predict(x).shape == y.shape
    pipe = fit_pipeline(ModelSpec("t", "texture", ("PC",), 200.0, "spatial"), x, y, g, seed=0)
    assert "stopped on the training loss" in _describe(pipe)


def test_texture_mlp_pipeline_uses_it():
    x, y, g = _trials()
    for features in ("spectral", "spatial"):
        pipe = fit_pipeline(ModelSpec("t", "texture", ("PC",), 200.0, features), x, y, g, seed=0)
        mlp = pipe.steps[-1][1]
        assert type(mlp) is MLPClassifier and len(mlp.validation_scores_) >= mlp.n_iter_ > 0
        np.testing.assert_allclose(pipe.steps[0][1].mean_, x.mean(axis=0), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="early_stopping"):
        fit_mlp_by_trials(x, y, g, early_stopping=True)
