"""Spike-train measures against brute force and against elephant's independent VR implementation."""

import warnings

import numpy as np
import pytest

from touchreal.analysis import spiketrains as stn


def _trains(rng, n_max=40, t=1.0):
    return np.sort(rng.uniform(0, t, rng.integers(0, n_max)))


def test_kernel_sum_matches_brute_force_including_ties_and_empty():
    rng = np.random.default_rng(1)
    for _ in range(300):
        x, y = _trains(rng), _trains(rng)
        if x.size and rng.random() < 0.4:
            y = np.sort(np.concatenate([y, x[: rng.integers(1, x.size + 1)]]))  # exact ties
        tau = float(rng.choice([0.0005, 0.001, 0.01, 0.2]))
        ref = stn.kernel_sum_bruteforce(x, y, tau)
        assert stn.kernel_sum(x, y, tau) == pytest.approx(ref, rel=1e-10, abs=1e-12)
        assert stn.kernel_sum(y, x, tau) == pytest.approx(ref, rel=1e-10, abs=1e-12)
    assert stn.kernel_sum(np.zeros(0), np.array([0.1]), 0.01) == 0.0
    # unsorted input is sorted unless presorted=True
    x = np.array([0.3, 0.1, 0.2])
    assert stn.kernel_sum(x, x, 0.05) == pytest.approx(stn.kernel_sum_bruteforce(x, x, 0.05))


def test_vr_distance_matches_elephant():
    quantities = pytest.importorskip("quantities")
    neo = pytest.importorskip("neo")
    from elephant.spike_train_dissimilarity import van_rossum_distance

    rng = np.random.default_rng(2)
    trains = [np.sort(rng.uniform(0, 2.0, n)) for n in (0, 1, 5, 37, 120)]
    trains.append(trains[3] + rng.normal(0, 0.0005, trains[3].size))  # jittered copy
    st = [neo.SpikeTrain(t * 1000.0, units="ms", t_stop=2500.0) for t in trains]  # ms: elephant's advice for precision
    for tau_s in (0.001, 0.01):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = van_rossum_distance(st, tau_s * 1000.0 * quantities.ms)
        ours = stn.vr_distance_matrix(trains, tau_s)
        np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-9)
        for i in range(len(trains)):
            for j in range(len(trains)):
                assert stn.vr_distance(trains[i], trains[j], tau_s) == pytest.approx(ref[i, j], rel=1e-9, abs=1e-9)
        between = stn.vr_distances_between(trains[:2], trains[2:], tau_s)
        np.testing.assert_allclose(between, ref[:2, 2:], rtol=1e-9, atol=1e-9)


def test_vr_normalisation_and_limits():
    assert stn.vr_distance(np.zeros(0), np.array([0.5]), 0.001) == pytest.approx(1.0)
    x = np.array([0.1, 0.2, 0.3])
    assert stn.vr_distance(x, x, 0.001) == 0.0
    # far-apart spikes: distance^2 = n1 + n2
    assert stn.vr_distance(x, x + 0.05, 0.0001) == pytest.approx(np.sqrt(6.0), rel=1e-6)


def test_kernel_distance_eq_2_to_5_hand_computed():
    tau = 0.01
    x = np.array([0.0])
    y = np.array([0.01])
    # A(x) = A(y) = 1, C = e^-1 -> sim = e^-1 / (1 + 1e-12)
    assert stn.kernel_similarity(x, y, tau) == pytest.approx(np.exp(-1.0), rel=1e-10)
    assert stn.kernel_distance(x, y, tau) == pytest.approx(1.0 - np.exp(-1.0), rel=1e-10)
    a = np.array([0.0, 0.02])
    # A(a) = 2 + 2 e^-2, C(a, x) = 1 + e^-2
    sim = (1 + np.exp(-2)) / np.sqrt(2 + 2 * np.exp(-2))
    assert stn.kernel_similarity(a, x, tau) == pytest.approx(sim, rel=1e-10)
    assert stn.kernel_distance(a, a, tau) == pytest.approx(0.0, abs=1e-12)
    assert stn.kernel_distance(a, np.zeros(0), tau) == 1.0
    assert stn.kernel_distance(np.zeros(0), np.zeros(0), tau) == 0.0
    assert stn.kernel_distance(np.zeros(0), np.zeros(0), tau, empty_pair=1.0) == 1.0
    rng = np.random.default_rng(3)
    for _ in range(50):
        p, q = _trains(rng) + 0.0, _trains(rng)
        d = stn.kernel_distance(p, q, tau)
        assert 0.0 <= d <= 1.0 + 1e-12


def test_rates_and_psth():
    t = np.array([0.05, 0.15, 0.16, 0.95, 1.2])
    assert stn.spike_count(t, 0.0, 1.0) == 4
    assert stn.firing_rate(t, 0.0, 1.0) == pytest.approx(4.0)
    centres, r = stn.psth([t, t[:2]], 0.0, 1.0, 0.1)
    assert centres.size == 10 and r.shape == (2, 10)
    np.testing.assert_allclose(r[0] * 0.1, [1, 2, 0, 0, 0, 0, 0, 0, 0, 1])
    _, rs = stn.psth([t], 0.0, 1.0, 0.01, smooth_s=0.02)
    assert rs.sum() * 0.01 == pytest.approx(4.0, rel=0.05)  # smoothing keeps the count (edges aside)
    with pytest.raises(ValueError):
        stn.firing_rate(t, 1.0, 1.0)
