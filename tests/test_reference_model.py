"""Reference model end to end: spike-for-spike against TouchSim's conformance data, plus sanity."""

from __future__ import annotations


import numpy as np
import pytest
from scipy import signal

import touchreal.reference.model as refmodel
from touchreal.reference.constants import load_constants
from touchreal.reference.model import ReferenceModel, reference_trains

FS = 5000.0
SAMPLE = 1.0 / FS


def _ramp(depth=1.0, v=40.0, hold=0.3, pre=0.05, post=0.1) -> np.ndarray:
    n_ramp = int(round(depth / v * FS))
    up = np.linspace(0, depth, n_ramp + 1)
    return np.concatenate([np.zeros(int(pre * FS)), up, np.full(int(hold * FS), depth), up[::-1],
                           np.zeros(int(post * FS))])


def _sine(freq, amp, dur=0.5, pre_indent=0.0) -> np.ndarray:
    t = np.arange(int(dur * FS)) / FS
    return pre_indent + amp * np.sin(2 * np.pi * freq * t)


# ---- self-contained ---------------------------------------------------------------------------


def test_reference_trains_layout_and_classes():
    out = reference_trains(_ramp(), repeats=3, noisy=True, seed=1)
    assert list(out) == ["SA1", "RA", "PC"]
    assert [out[c].n_models for c in out] == [4, 9, 4]
    assert all(out[c].repeats == 3 for c in out)
    for ref in out.values():
        for tr in ref.trains():
            assert np.all(np.diff(tr) >= 5 * SAMPLE)  # refractory: >= 6 samples apart (float32 times)
            assert tr.size == 0 or (tr[0] > 0 and tr[-1] <= _ramp().size / FS + 1e-6)


def test_noiseless_is_deterministic_and_repeats_identical():
    a = reference_trains(_ramp(), repeats=3, noisy=False)
    b = reference_trains(_ramp(), repeats=1, noisy=False, seed=123)
    for cls in a:
        trains = a[cls].trains()
        n = a[cls].n_models
        for r in range(1, 3):
            for m in range(n):
                np.testing.assert_array_equal(trains[r * n + m], trains[m])
        np.testing.assert_array_equal(a[cls].off[0], b[cls].off[0])
        np.testing.assert_array_equal(a[cls].t[: b[cls].t.size], b[cls].t)


def test_noise_is_seeded_and_independent_across_repeats():
    x = _sine(100, 0.05, pre_indent=0.3)
    a = reference_trains(x, repeats=4, seed=7)
    b = reference_trains(x, repeats=4, seed=7)
    c = reference_trains(x, repeats=4, seed=8)
    for cls in a:
        np.testing.assert_array_equal(a[cls].t, b[cls].t)
        np.testing.assert_array_equal(a[cls].off, b[cls].off)
    assert any(a[k].t.size != c[k].t.size or not np.array_equal(a[k].t, c[k].t) for k in a)
    ra = a["RA"]  # repeats differ from each other
    assert len({tuple(np.round(ra.train(r, 0), 6)) for r in range(4)}) > 1


def test_delays_shift_every_train_by_its_model_delay():
    x = _ramp(depth=0.8, v=65.0)
    model = ReferenceModel()
    plain = model.simulate(x, noisy=False, delays=False)
    delayed = model.simulate(x, noisy=False, delays=True)
    np.testing.assert_array_equal(plain.off, delayed.off)
    delay_s = load_constants().params[:, 12] / 1000.0
    for m in range(17):
        np.testing.assert_allclose(delayed.train(0, 0, m), plain.train(0, 0, m) + delay_s[m], atol=1e-12)


def test_class_signatures_of_a_ramp_and_a_vibration():
    x = _ramp(depth=1.0, v=40.0, hold=0.5)
    model = ReferenceModel()
    r = model.simulate(x, noisy=False)
    n_pre, n_ramp = int(0.05 * FS), int(round(1.0 / 40.0 * FS))
    hold = ((n_pre + n_ramp) / FS + 0.15, (n_pre + n_ramp) / FS + 0.5)
    in_hold = lambda tr: int(np.sum((tr > hold[0]) & (tr < hold[1])))  # noqa: E731
    sa1 = [in_hold(r.train(0, 0, m)) for m in range(4)]
    ra = [in_hold(r.train(0, 0, m)) for m in range(4, 13)]
    assert min(sa1) > 5  # SA1 keeps firing during the hold
    assert sum(ra) == 0  # RA is silent during the hold ...
    assert all(r.train(0, 0, m).size > 0 for m in range(4, 13))  # ... and fires on the transients
    # PC: a 250 Hz, 10 um vibration drives PC fibres, not SA1
    v = model.simulate(_sine(250, 0.01, pre_indent=0.2), noisy=False)
    counts = v.counts()[0, 0]
    assert counts[13:].min() > 20 and counts[:4].max() < counts[13:].min()


def test_responses_fall_with_distance():
    model = ReferenceModel()
    aff = np.array([[0.0, 0.0], [2.0, 0.0], [6.0, 0.0]])
    r = model.simulate(_ramp(depth=1.0), probe_xy_mm=(0.0, 0.0), afferent_xy_mm=aff, noisy=False)
    per_class = np.add.reduceat(r.counts()[0], [0, 4, 13], axis=1)  # (L, 3)
    assert np.all(np.diff(per_class, axis=0) <= 0)
    assert per_class[0, 0] > per_class[2, 0] and per_class[0, 1] > per_class[2, 1]


def test_many_locations_blocks_and_single_location_agree(monkeypatch):
    x = _sine(60, 0.1, dur=0.3, pre_indent=0.2)
    aff = np.array([[0.0, 0.0], [1.0, 1.0], [3.0, -2.0]])
    model = ReferenceModel()
    together = model.simulate(x, probe_xy_mm=(0.5, 0.0), afferent_xy_mm=aff, noisy=False, repeats=2)
    monkeypatch.setattr(refmodel, "MAX_BLOCK_ELEMENTS", x.size * 17)  # one location per LIF block
    blocked = model.simulate(x, probe_xy_mm=(0.5, 0.0), afferent_xy_mm=aff, noisy=False, repeats=2)
    np.testing.assert_array_equal(together.off, blocked.off)
    np.testing.assert_array_equal(together.t, blocked.t)
    for loc in range(3):
        single = model.simulate(x, probe_xy_mm=(0.5, 0.0), afferent_xy_mm=aff[loc:loc + 1], noisy=False)
        for m in range(17):
            np.testing.assert_array_equal(single.train(0, 0, m), together.train(1, loc, m))


def test_other_sampling_rates_are_resampled_to_5khz():
    x5 = _ramp(depth=0.5, v=20.0)
    x10 = np.interp(np.arange(2 * x5.size - 1) / 10000.0, np.arange(x5.size) / FS, x5)
    a = reference_trains(x5, noisy=False)
    b = reference_trains(x10, fs_hz=10000.0, noisy=False)
    for cls in a:
        np.testing.assert_array_equal(a[cls].off, b[cls].off)
        np.testing.assert_array_equal(a[cls].t, b[cls].t)


def test_rest_gives_no_noiseless_spikes_and_bad_input_is_rejected():
    out = reference_trains(np.zeros(2000), noisy=False)
    assert all(out[c].t.size == 0 for c in out)
    with pytest.raises(ValueError):
        reference_trains(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError):
        reference_trains(np.zeros((10, 2)))
    with pytest.raises(ValueError):
        ReferenceModel().simulate(np.zeros(10), repeats=0)


# ---- against TouchSim's conformance data ------------------------------------------------------



@pytest.mark.shared
def test_noiseless_spikes_match_touchsim_spike_for_spike(conformance):
    root, stimuli = conformance
    model = ReferenceModel(pin_radius_mm=0.5)
    n_total = n_within = 0
    for s in stimuli:
        with np.load(root / s["file"]) as d:
            assert float(d["pin_radius"]) == 0.5 and float(d["fs"]) == FS
            r = model.simulate(d["trace"], probe_xy_mm=d["probe_xy"], afferent_xy_mm=d["aff_xy"], noisy=False)
            assert r.model_class.tolist() == d["model_class"].tolist()
            np.testing.assert_array_equal(r.model_index, d["model_index"])
            # counts equal for every location and model (offset tables identical)
            np.testing.assert_array_equal(r.off, d["spikes_off"], err_msg=s["id"])
            diff = np.abs(r.t - d["spikes_t"])
            n_total += diff.size
            n_within += int(np.sum(diff <= 0.5 * SAMPLE))
            assert diff.max(initial=0.0) < 1e-12, s["id"]  # same sample, same float
            if "delay_spikes_t" in d.files:
                rd = model.simulate(d["trace"], probe_xy_mm=d["probe_xy"], afferent_xy_mm=d["aff_xy"],
                                    noisy=False, delays=True)
                np.testing.assert_array_equal(rd.off, d["delay_spikes_off"], err_msg=s["id"])
                assert np.abs(rd.t - d["delay_spikes_t"]).max(initial=0.0) < 1e-12
    assert n_total == 28_272 and n_within == n_total


def _vr_pairs(trains: list[np.ndarray], n_samples: int, tau: float = 1e-3) -> np.ndarray:
    """Van Rossum distances of all pairs (elephant normalisation: sqrt(A(x) + A(y) - 2 C(x, y))).

    Exact for trains on the 5 kHz grid: kernel sums via a Gram matrix of spike-count rows.
    """
    idx = [np.rint(np.asarray(tr, dtype=np.float64) * FS).astype(int) for tr in trains]
    h = np.zeros((len(trains), n_samples + 2))
    for i, ix in enumerate(idx):
        np.add.at(h[i], ix, 1.0)
    lag = np.arange(-int(40 * tau * FS), int(40 * tau * FS) + 1)
    k = np.exp(-np.abs(lag) / (tau * FS))
    hk = signal.oaconvolve(h, k[None, :], mode="same", axes=1)  # kernel-smoothed trains
    gram = np.stack([hk[:, ix].sum(axis=1) for ix in idx])  # C(x_i, x_j), no BLAS
    d = np.diag(gram)
    d2 = d[:, None] + d[None, :] - 2 * gram
    iu = np.triu_indices(len(trains), 1)
    return np.sqrt(np.maximum(d2[iu], 0.0))


@pytest.mark.shared
def test_noisy_statistics_match_touchsim(conformance):
    """Mean spike counts within 5 % and the same spread of van Rossum distances between repeats."""
    root, stimuli = conformance
    model = ReferenceModel()
    repeats = 20
    pooled = {c: np.zeros(2) for c in ("SA1", "RA", "PC")}
    vr = {c: ([], []) for c in ("SA1", "RA", "PC")}
    n_cells = 0
    for s in stimuli:
        with np.load(root / s["file"]) as d:
            if "noisy_spikes_t" not in d.files:
                continue
            t_ts, off_ts = d["noisy_spikes_t"], d["noisy_spikes_off"]
            ours = model.simulate(d["trace"], probe_xy_mm=d["probe_xy"], afferent_xy_mm=d["noisy_aff_xy"],
                                  noisy=True, repeats=repeats, rng=2024)
            n_t = d["trace"].size
        c_ts, c_us = np.diff(off_ts, axis=2), ours.counts()
        for cls, sl in (("SA1", slice(0, 4)), ("RA", slice(4, 13)), ("PC", slice(13, 17))):
            for loc in range(off_ts.shape[1]):
                a = c_ts[:, loc, sl].sum(axis=1).mean()
                b = c_us[:, loc, sl].sum(axis=1).mean()
                pooled[cls] += (a, b)
                if a >= 30:  # enough spikes for a 5 % comparison of 10-repeat means
                    n_cells += 1
                    assert abs(b / a - 1) <= 0.05, (s["id"], loc, cls, a, b)
                for m in range(sl.start, sl.stop):
                    vr[cls][0].append(_vr_pairs([t_ts[off_ts[r, loc, m]:off_ts[r, loc, m + 1]]
                                                 for r in range(off_ts.shape[0])], n_t))
                    vr[cls][1].append(_vr_pairs([ours.train(r, loc, m) for r in range(repeats)], n_t))
    assert n_cells >= 25
    for cls, (a, b) in pooled.items():
        assert abs(b / a - 1) <= 0.02, (cls, a, b)
    for cls, (ts, us) in vr.items():
        ts, us = np.concatenate(ts), np.concatenate(us)
        assert ts.mean() > 0.5
        assert abs(us.mean() / ts.mean() - 1) <= 0.15, (cls, ts.mean(), us.mean())
        np.testing.assert_allclose(np.percentile(us, [50, 75, 90]), np.percentile(ts, [50, 75, 90]),
                                   rtol=0.2, atol=0.1, err_msg=cls)
