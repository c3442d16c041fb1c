"""The shared feature module (touchreal_client.features) and the in-graph feature definitions."""

from __future__ import annotations

import numpy as np
import pytest
from touchreal_client import features as F

from touchreal.decoding.features import FeatureSpec


def brute_counts(t: np.ndarray, end: int, window: int, bin_us: int) -> list[int]:
    """Bins counted back from the end one by one, oldest (possibly short) bin first."""
    out, hi = [], end
    while hi > end - window:
        lo = max(hi - bin_us, end - window)
        out.append(int(np.sum((t >= lo) & (t < hi))))
        hi = lo
    return out[::-1]


@pytest.mark.parametrize("window", [4_000, 10_000, 16_000, 128_000, 500_000])
def test_window_counts_match_brute_force(window):
    rng = np.random.default_rng(1)
    t = np.sort(rng.integers(0, 2_000_000, 400))
    t[10] = t[11]  # a duplicate time counts twice
    ends = np.array([window, 123_456 + window, 1_000_000, 1_990_000])
    got = F.window_counts(t, ends, window)
    assert got.shape == (4, F.n_bins(window))
    assert got.dtype == np.float32
    for row, end in zip(got, ends):
        assert row.tolist() == brute_counts(t, int(end), window, F.BIN_US)


def test_bins_oldest_short_and_boundaries():
    assert F.n_bins(128_000) == 13 and F.n_bins(4_000) == 1 and F.n_bins(500_000) == 50
    edges = F.bin_edges(np.array([1_000_000]), 128_000)[0]
    assert edges[0] == 872_000 and edges[1] == 880_000 and np.all(np.diff(edges[1:]) == 10_000) and edges[-1] == 1_000_000
    # a spike exactly at the end belongs to the next window, one at the start to this one
    c = F.window_counts(np.array([872_000, 1_000_000]), np.array([1_000_000]), 128_000)[0]
    assert c[0] == 1 and c.sum() == 1


def test_step_times_and_anchors():
    assert F.step_times(1, 100_000).tolist() == [32_000, 64_000, 96_000]
    assert F.step_times(0, 64_000).tolist() == [0, 32_000, 64_000]
    t = np.array([100_000, 150_000, 700_000, 710_000, 1_300_000])
    assert F.anchors(t, 500_000).tolist() == [100_000, 700_000, 1_300_000]
    ends, anchor = F.anchored_end(np.array([50_000, 100_000, 135_000, 705_000]), F.anchors(t, 500_000))
    assert anchor.tolist() == [-1, -1, 100_000, 700_000]  # an anchor counts from the step after it
    assert ends.tolist() == [-1, -1, 130_000, 700_000]
    assert F.ready(np.array([130_000, 600_000]), np.array([100_000, 100_000]), 500_000).tolist() == [False, True]


def test_temporal_features_are_normalised_smoothing():
    spec = FeatureSpec("temporal", 50, 1, 10.0, 500.0)
    s = spec.smoothing()
    assert np.allclose(s.sum(axis=1), 1.0)
    counts = np.ones((2, 50, 1), np.float32) * 3
    assert np.allclose(spec.transform(counts), 3.0, atol=1e-5)  # constant in, constant out (edges too)


def test_rate_features_match_their_definitions():
    spec = FeatureSpec("rate", 50, 1, 10.0, 500.0)
    rng = np.random.default_rng(2)
    c = rng.poisson(1.0, (3, 50, 1)).astype(np.float32)
    f = spec.transform(c)
    x = c[:, :, 0].astype(np.float64)
    assert spec.names()[:3] == ["rate_hz", "count_var", "frac_nonempty"]
    assert np.allclose(f[:, 0], x.sum(1) / 0.5, rtol=1e-5)
    assert np.allclose(f[:, 1], x.var(1), rtol=1e-4, atol=1e-5)
    assert np.allclose(f[:, 2], (x > 0).mean(1), rtol=1e-6)
    mag = np.abs(np.fft.rfft(x, axis=1))[:, 1:] / 50  # bins k = 1..25 at 2 Hz spacing
    freq = np.arange(1, 26) * 2.0
    for b, (lo, hi) in enumerate([(0, 10), (10, 20), (20, 30), (30, 40), (40, 50)]):
        sel = (freq > lo) & (freq <= hi)
        assert np.allclose(f[:, 3 + b], mag[:, sel].mean(1), rtol=1e-4, atol=1e-6)


def test_feature_spec_rejects_bad_shapes():
    with pytest.raises(ValueError, match="one class"):
        FeatureSpec("temporal", 50, 2, 10.0, 500.0)
    with pytest.raises(ValueError, match="counts must be"):
        FeatureSpec("counts", 13, 2, 10.0, 128.0).transform(np.zeros((1, 12, 2)))
