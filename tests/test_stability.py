"""Numerical stability under hostile input: nothing non-finite, bounded state, flat memory."""

import numpy as np
import pytest

from touchreal.params import default_params
from touchreal.raw import RawChunk
from touchreal.stream import StreamEncoder


def _stream(seconds, chunk_s, make_st, make_pv, n_taxels=2, seed=0):
    """Yield RawChunks of ``chunk_s`` from sample generators f(t, rng) -> (n, taxels)."""
    rng = np.random.default_rng(seed)
    chunk_ms = int(round(chunk_s * 1000))
    for i in range(int(round(seconds * 1000)) // chunk_ms):
        a, b = i * chunk_ms, (i + 1) * chunk_ms  # integer sample bounds: no rounding duplicates
        st_t = np.arange(a * 100 // 1000, b * 100 // 1000) / 100 + 0.002
        pv_t = np.arange(a * 2, b * 2) / 2000 + 0.0001
        yield RawChunk(st_t, make_st(st_t, rng, n_taxels), pv_t, make_pv(pv_t, rng, n_taxels))


def test_hostile_input_never_reaches_state():
    se = StreamEncoder(default_params(), n_taxels=2)

    def st(t, rng, n):
        x = 5 + 5 * np.sign(np.sin(2 * np.pi * 3 * t))[:, None] * np.ones(n)  # 0 <-> 10 N steps
        x[rng.uniform(size=x.shape) < 0.1] = np.nan
        x[rng.uniform(size=x.shape) < 0.05] = np.inf
        x[rng.uniform(size=x.shape) < 0.05] = 1e6  # far out of range
        return x

    def pv(t, rng, n):
        x = 1.65 * np.sign(np.sin(2 * np.pi * 400 * t))[:, None] * np.ones(n)  # rail to rail
        x[rng.uniform(size=x.shape) < 0.05] = -np.inf
        x[rng.uniform(size=x.shape) < 0.05] = np.nan
        return x

    spikes = 0
    for chunk in _stream(5.0, 0.032, st, pv):
        ev = se.process(chunk)
        spikes += len(ev)
        assert np.all(np.isfinite(ev.t_s))
        finite, peak, _ = se.state_report()
        assert finite and peak < 1e4
    stats = se.stats
    assert stats["singletact"]["non_finite"] > 0 and stats["singletact"]["out_of_range"] > 0
    assert stats["pvdf"]["non_finite"] > 0
    assert spikes > 0


def test_gaps_and_duplicates_are_repaired_and_counted():
    se = StreamEncoder(default_params())
    chunks = list(_stream(2.0, 0.032, lambda t, r, n: np.ones((t.size, n)), lambda t, r, n: 0.01 * np.sin(200 * t)[:, None], 1))
    del chunks[20:25]  # a 160 ms outage
    chunks.insert(30, chunks[29])  # a repeated packet
    for c in chunks:
        se.process(c)
    se.finish()
    st = se.stats
    assert st["pvdf"]["gaps"] == 1 and st["pvdf"]["gap_filled"] == 320
    assert st["singletact"]["duplicate"] >= 3 and st["pvdf"]["duplicate"] == 64
    assert se.state_report()[0]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_long_stream_state_bounded_and_memory_flat(dtype):
    """Ten minutes of a saturating press/vibration loop: state and buffers stay the same size (both dtypes)."""
    se = StreamEncoder(default_params(), n_taxels=1, dtype=dtype)
    st = lambda t, r, n: (10 * (np.sin(2 * np.pi * 0.5 * t) > 0) + r.normal(0, 0.02, t.size))[:, None]
    pv = lambda t, r, n: (1.6 * np.sin(2 * np.pi * 300 * t) * (np.sin(2 * np.pi * 0.25 * t) > 0) + r.normal(0, 0.01, t.size))[:, None]
    sizes, peaks = [], []
    for i, chunk in enumerate(_stream(600.0, 0.5, st, pv, n_taxels=1)):
        se.process(chunk)
        if i % 100 == 99:
            finite, peak, nbytes = se.state_report()
            assert finite
            sizes.append(nbytes)
            peaks.append(peak)
    half = len(sizes) // 2
    assert max(sizes[half:]) <= max(sizes[:half])  # buffers are bounded: nothing grows over time
    assert max(peaks) < 1e4 and max(peaks[len(peaks) // 2 :]) <= 1.05 * max(peaks[: len(peaks) // 2])
