"""Invariants of the causal preprocessing stages (sanitize, filters, alpha-beta, STFT gate, PCHIP)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import signal
from scipy.interpolate import PchipInterpolator

from touchreal.params import GateCalibration, PreprocessParams
from touchreal.preprocess.filters import (HUM_HISTORY_S, AlphaBeta, SosFilter, butter_lowpass, mains_notches, periodic_history,
                                          prime_with_hum)
from touchreal.preprocess.gate import calibrate, detect_harmonics, gate_thresholds
from touchreal.preprocess.resample import CausalPchip
from touchreal.preprocess.sanitize import Sanitizer
from touchreal.preprocess.stft_gate import StftGate, frame_length

FS = 2000.0


def _split_points(draw_sizes, n):
    cuts, pos = [0], 0
    for s in draw_sizes:
        pos += s
        if pos >= n:
            break
        cuts.append(pos)
    cuts.append(n)
    return cuts


def _run_chunked(process, x, cuts):
    return np.concatenate([process(x[a:b]) for a, b in zip(cuts, cuts[1:])], axis=0)


signals = arrays(np.float64, st.integers(20, 400), elements=st.floats(-5, 5))
sizes = st.lists(st.integers(0, 50), min_size=1, max_size=30)


@settings(max_examples=40, deadline=None)
@given(x=signals, sz=sizes)
def test_sos_filter_is_chunk_invariant(x, sz):
    whole = butter_lowpass(100.0, FS, 4).process(x[:, None])
    f = butter_lowpass(100.0, FS, 4)
    chunked = _run_chunked(f.process, x[:, None], _split_points(sz, x.size))
    np.testing.assert_array_equal(whole, chunked)


def test_sos_filter_starts_in_steady_state():
    y = butter_lowpass(20.0, 100.0, 2).process(np.full((50, 3), 0.5))
    np.testing.assert_allclose(y, 0.5, atol=1e-12)
    sos = signal.butter(2, 20.0, fs=100.0, output="sos")
    primed = SosFilter(sos, 2, initial=np.array([1.0, 2.0])).process(np.tile([1.0, 2.0], (30, 1)))
    np.testing.assert_allclose(primed, np.tile([1.0, 2.0], (30, 1)), atol=1e-12)  # no transient at the known level
    step = SosFilter(sos, 1, initial=np.array([0.0])).process(np.ones((30, 1)))
    assert step[0, 0] < 0.5 and abs(step[-1, 0] - 1.0) < 1e-3  # starting at 0, a step is filtered


def test_notch_bank_removes_only_selected_harmonics():
    t = np.arange(8000) / FS
    x = np.sin(2 * np.pi * 150 * t) + np.sin(2 * np.pi * 100 * t)
    y = mains_notches(50.0, [1, 3, 5], 30.0, FS).process(x[:, None])[4000:, 0]
    f, p = signal.periodogram(y, FS)
    p100, p150 = p[np.argmin(abs(f - 100))], p[np.argmin(abs(f - 150))]
    assert p150 < 1e-4 * p100  # 150 Hz notched by > 40 dB, 100 Hz kept
    assert mains_notches(50.0, [30], 30.0, FS) is None  # 1500 Hz is above Nyquist


def _hum(k: np.ndarray) -> np.ndarray:
    """A constant plus 50/150/250 Hz hum at 2 kHz, two taxels with different phases: (len(k), 2)."""
    t = np.asarray(k, np.float64)[:, None] / FS
    return 0.01 + 0.010 * np.sin(2 * np.pi * 50 * t + [0.3, 2.0]) + 0.005 * np.sin(2 * np.pi * 150 * t + [1.0, -1.0]) + 0.002 * np.cos(2 * np.pi * 250 * t)


def test_periodic_history_extrapolates_a_constant_plus_hum_into_the_past():
    past = periodic_history(_hum(np.arange(200)), FS, [50.0, 150.0, 250.0, 350.0], 1500)
    np.testing.assert_allclose(past, _hum(np.arange(-1500, 0)), atol=1e-9)
    # frequencies at or above Nyquist are ignored; a block too short for the sinusoids gives its mean
    np.testing.assert_allclose(periodic_history(_hum(np.arange(200)), FS, [50.0, 150.0, 250.0, 1000.0, 3000.0], 10)[:, 0], _hum(np.arange(-10, 0))[:, 0], atol=1e-9)
    short = np.array([[1.0], [3.0], [2.0]])
    np.testing.assert_allclose(periodic_history(short, FS, [50.0, 150.0], 4), 2.0)
    with pytest.raises(ValueError):
        periodic_history(np.zeros((0, 1)), FS, [50.0], 4)


def test_notches_primed_with_the_hum_start_without_ringing():
    bank = lambda: butter_lowpass(800.0, FS, 4, 2).then(mains_notches(50.0, [1, 3, 5], 30.0, FS, 2))  # noqa: E731
    x = _hum(np.arange(1000))
    cold = bank().process(x)  # steady state for the first sample only: the notches ring for ~0.2 s
    primed = bank()
    primed.prime(periodic_history(x[:200], FS, [50.0, 150.0, 250.0], 2000))
    warm = primed.process(x)
    assert np.abs(cold[:100] - 0.01).max() > 5e-3  # the old start: half the hum passes
    # primed: only the constant passes from sample 0, up to the ringing left after the 1 s history
    # (exp(-1 s / 0.19 s) = 0.5 % of the 10 mV at 50 Hz)
    np.testing.assert_allclose(warm, 0.01, atol=1e-4)
    # priming with the exact past equals having filtered that past
    longer = bank().process(_hum(np.arange(-2000, 1000)))[2000:]
    np.testing.assert_allclose(warm, longer, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_priming_with_the_hum_sets_the_state_filtering_its_past_leaves(dtype):
    """prime_with_hum applies one operator per cascade and block length (the fit and the filtering of
    the synthetic past, done once on unit blocks): the state equals priming with periodic_history,
    up to rounding, for any taxels, block lengths (a short block: the constant alone) and dtype."""
    freqs = [50.0, 150.0, 250.0]
    bank = lambda n: butter_lowpass(800.0, FS, 4, n, dtype).then(mains_notches(50.0, [1, 3, 5], 30.0, FS, n, dtype))  # noqa: E731
    rng = np.random.default_rng(1)
    for n_taxels, n in ((2, 200), (5, 200), (3, 7), (1, 1)):
        x = (_hum(np.arange(n))[:, :1] * rng.uniform(0.5, 2.0, n_taxels)) + rng.normal(0, 1e-3, (n, n_taxels))
        want, got = bank(n_taxels), bank(n_taxels)
        want.prime(periodic_history(x, FS, freqs, int(round(HUM_HISTORY_S * FS))))
        prime_with_hum(got, x, FS, freqs)
        assert got.zi.dtype == np.dtype(dtype) and got.zi.shape == want.zi.shape
        np.testing.assert_allclose(got.zi, want.zi, rtol=0, atol=1e-12 if dtype == np.float64 else 1e-5)
        y = rng.normal(0, 1e-3, (400, n_taxels))
        np.testing.assert_allclose(got.process(y), want.process(y), rtol=0, atol=1e-12 if dtype == np.float64 else 1e-5)
    with pytest.raises(ValueError):
        prime_with_hum(bank(1), np.zeros((0, 1)), FS, freqs)


def test_alpha_beta_tracks_a_ramp_and_rejects_unstable_gains():
    t = np.arange(300) / 100.0
    x, v = AlphaBeta(0.5, 0.1, 100.0).process((2.0 * t)[:, None])
    assert abs(v[-1, 0] - 2.0) < 1e-6 and abs(x[-1, 0] - 2.0 * t[-1]) < 1e-3
    x, v = AlphaBeta(0.5, 0.1, 100.0).process(np.full((300, 1), 3.0))
    assert np.all(v == 0) and np.all(x == 3.0)
    with pytest.raises(ValueError, match="stable"):
        AlphaBeta(0.5, 3.5, 100.0)


@settings(max_examples=30, deadline=None)
@given(x=signals, sz=sizes)
def test_alpha_beta_chunk_invariant(x, sz):
    ab = AlphaBeta(0.5, 0.1, 100.0)
    whole = np.hstack(ab.process(x[:, None]))
    ab2 = AlphaBeta(0.5, 0.1, 100.0)
    chunked = _run_chunked(lambda c: np.hstack(ab2.process(c)), x[:, None], _split_points(sz, x.size))
    np.testing.assert_array_equal(whole, chunked)


@pytest.mark.parametrize("window_ms", [4, 8, 16, 32, 64, 128, 256, 512])
def test_stft_gate_without_threshold_is_identity_on_the_clock(window_ms):
    n = frame_length(window_ms, FS)
    x = np.random.default_rng(1).normal(size=(3000, 2))
    y = StftGate(n, 2).process(x)
    h = n // 4
    assert y.shape[0] == (3000 // h) * h - (n - h)  # final once every covering frame is done
    np.testing.assert_allclose(y, x[: y.shape[0]], atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(x=signals, sz=sizes, thr=st.floats(0.0, 3.0))
def test_stft_gate_chunk_invariant(x, sz, thr):
    n = 32
    make = lambda: StftGate(n, 1, np.full(n // 2 + 1, thr), 0.1)
    whole = make().process(x[:, None])
    g = make()
    chunked = _run_chunked(g.process, x[:, None], _split_points(sz, x.size))
    np.testing.assert_array_equal(whole, chunked)


def test_gate_suppresses_noise_and_keeps_a_tone():
    rng = np.random.default_rng(2)
    t = np.arange(40000) / FS
    raw = rng.normal(0, 0.01, t.size)
    params = calibrate([raw[:8000]], PreprocessParams(notch_harmonics=[]))
    noise = butter_lowpass(params.pvdf_lowpass_hz, FS, 4).process(raw[:, None])[:, 0]  # as in the pipeline
    assert params.notch_harmonics == []
    n = frame_length(128, FS)
    gate = StftGate(n, 1)
    thr = gate_thresholds(params.gate, gate.window, FS)
    tone = 0.05 * np.sin(2 * np.pi * 300 * t)
    g = StftGate(n, 1, thr, params.gate.attenuation)
    y = g.process((tone + noise)[:, None])[:, 0]
    m = y.size
    err_in = np.std(noise[:m])
    err_out = np.std(y[n:] - tone[n:m])
    assert err_out < 0.5 * err_in  # broadband noise reduced by more than half
    amp_out = np.sqrt(2) * np.std(y[n:])
    assert 0.045 < amp_out < 0.056  # tone kept
    assert StftGate(n, 1, thr).process(noise[:, None]).std() < 0.2 * noise.std()


def test_harmonic_detection_finds_only_lines_above_the_floor():
    rng = np.random.default_rng(3)
    t = np.arange(20000) / FS
    x = rng.normal(0, 0.003, t.size) + 0.01 * np.sin(2 * np.pi * 50 * t) + 0.005 * np.sin(2 * np.pi * 250 * t)
    f, p = signal.welch(x, FS, nperseg=256)
    assert detect_harmonics(f, p, 50.0, FS) == [1, 5]
    assert calibrate([x], PreprocessParams()).notch_harmonics == [1, 5]


def test_thresholds_scale_with_window_energy():
    gate = GateCalibration(freqs_hz=[0, 1000], noise_asd=[1e-3, 1e-3], factor=2)
    small, big = (gate_thresholds(gate, signal.get_window("hann", n), FS) for n in (64, 256))
    np.testing.assert_allclose(big[::4] / small, 2.0, rtol=0.02)  # sqrt of the 4x window energy


def test_pchip_matches_scipy_inside_and_is_chunk_invariant():
    rng = np.random.default_rng(4)
    t = 0.003 + np.arange(60) / 100.0
    y = np.cumsum(rng.normal(size=(60, 2)), axis=0)
    whole = CausalPchip(5000.0, 2)
    k0, out = whole.process(t, y)
    tk = (k0 + np.arange(out.shape[0])) / 5000.0
    assert tk[0] >= t[1] and tk[-1] < t[-2]
    np.testing.assert_allclose(out, PchipInterpolator(t, y, axis=0)(tk), rtol=1e-12, atol=1e-12)
    pieces = CausalPchip(5000.0, 2)
    got = [pieces.process(t[i : i + 1], y[i : i + 1]) for i in range(60)]
    got = [g for g in got if g[1].shape[0]]
    assert got[0][0] == k0
    np.testing.assert_array_equal(np.concatenate([g[1] for g in got]), out)


@settings(max_examples=60, deadline=None)
@given(
    x=arrays(np.float64, st.integers(1, 200), elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
    jitter=st.lists(st.sampled_from([0.0, 0.0, 0.0, -1.0, 2.0, np.nan]), min_size=200, max_size=200),
)
def test_sanitizer_output_is_finite_in_range_and_on_the_grid(x, jitter):
    t = 0.0021 + np.arange(x.size) / 100.0 + np.array(jitter[: x.size]) / 100.0
    s = Sanitizer(100.0, (0.0, 10.0))
    first, y = s.push(t, x)
    assert np.all(np.isfinite(y)) and np.all((y >= 0) & (y <= 10))
    assert first == 0 and s.next_slot == y.shape[0]
    st_ = s.stats
    assert st_.accepted + st_.duplicate + st_.bad_time == x.size
    assert st_.accepted + st_.gap_filled == y.shape[0]


def test_sanitizer_policy_counts_each_repair():
    s = Sanitizer(100.0, (0.0, 10.0))
    t = np.array([0.00, 0.01, 0.01, np.nan, 0.02, 0.05, 0.04, 0.06])
    x = np.array([1.0, np.nan, 5.0, 5.0, 12.0, 4.0, 3.0, np.inf])
    first, y = s.push(t, x)
    np.testing.assert_allclose(y[:, 0], [1.0, 1.0, 10.0, 8.0, 6.0, 4.0, 4.0])
    assert s.stats.as_dict() == {
        "accepted": 5, "bad_time": 1, "duplicate": 2, "non_finite": 2, "out_of_range": 1, "gaps": 1, "gap_filled": 2,
    }
    # next chunk continues on the same grid; a late sample is dropped
    first, y = s.push(np.array([0.055, 0.07]), np.array([2.0, 2.0]))
    assert first == 7 and y.shape == (1, 1) and s.stats.duplicate == 3


def test_a_clean_block_passes_the_sanitizer_as_a_new_float64_array_whatever_its_dtype():
    """The fast path (finite, in range, no gap): float32 samples come out as their float64 values,
    in an array of the sanitizer's own (the caller may reuse its buffer), with the same counts as the
    same samples in float64; a block needing a repair still gets it."""
    rng = np.random.default_rng(3)
    t = np.arange(64) / 2000.0
    x = rng.normal(0.0, 0.5, (64, 5)).astype(np.float32)
    a, b = Sanitizer(2000.0, (-5.0, 5.0), 5), Sanitizer(2000.0, (-5.0, 5.0), 5)
    _, ya = a.push(t, x)
    _, yb = b.push(t, x.astype(np.float64))
    assert ya.dtype == np.float64 and not np.shares_memory(ya, x)
    np.testing.assert_array_equal(ya, yb)
    kept = ya.copy()
    x[:] = 0.0  # the caller reuses its buffer
    np.testing.assert_array_equal(ya, kept)
    assert a.stats.as_dict() == b.stats.as_dict() == {**a.stats.as_dict(), "accepted": 320}
    y64 = np.full((64, 5), 1.0)
    _, same = a.push(t + 64 / 2000.0, y64)
    assert not np.shares_memory(same, y64)
    x[10, 2], x[20, 4] = np.nan, 7.0  # one non-finite, one beyond the range
    _, y = a.push(t + 128 / 2000.0, x)
    assert y[10, 2] == y[9, 2] and y[20, 4] == 5.0
    assert a.stats.non_finite == 1 and a.stats.out_of_range == 1


@settings(max_examples=30, deadline=None)
@given(x=arrays(np.float64, st.tuples(st.integers(1, 300), st.integers(1, 3)), elements=st.floats(-10, 10)))
def test_sos_kernel_equals_scipy_sosfilt(x):
    sos = np.vstack((signal.butter(4, 300, fs=FS, output="sos"), signal.tf2sos(*signal.iirnotch(150, 30, fs=FS))))
    f = SosFilter(sos, x.shape[1])
    zi0 = signal.sosfilt_zi(sos)[:, :, None] * x[0][None, None, :]
    want, _ = signal.sosfilt(sos, x, axis=0, zi=zi0)
    np.testing.assert_allclose(f.process(x), want, rtol=1e-12, atol=1e-12)


def test_history_ring_keeps_the_newest_samples_by_slot():
    from touchreal.preprocess.branches import History

    h = History(5, 2)
    assert h.first is None
    x = np.arange(16.0).reshape(8, 2)
    h.push(10, x[:3])
    h.push(13, x[3:8])  # wraps around: slots 13..17, only 5 kept
    assert h.first == 13
    first, got = h.since(0)
    assert first == 13 and np.array_equal(got, x[3:8])
    assert np.array_equal(h.since(16)[1], x[6:8])
    with pytest.raises(ValueError, match="contiguous"):
        h.push(20, x[:1])
    h.clear()
    h.push(20, x[:1])  # after clear any slot starts the history again
    assert h.first == 20


def test_thread_count_follows_the_environment_and_split_run_covers_every_item(monkeypatch):
    import threading

    from touchreal.preprocess import parallel

    try:
        for text, want in (("1", 1), ("3", 3), ("0", 1)):
            monkeypatch.setenv(parallel.THREADS_ENV, text)
            parallel.default_thread_count.cache_clear()
            assert parallel.thread_count() == want
        monkeypatch.setenv(parallel.THREADS_ENV, "two")
        parallel.default_thread_count.cache_clear()
        with pytest.raises(ValueError, match="TOUCHREAL_THREADS"):
            parallel.thread_count()
        monkeypatch.delenv(parallel.THREADS_ENV)
        parallel.default_thread_count.cache_clear()
        assert 1 <= parallel.thread_count() <= parallel.MAX_THREADS
        parallel.set_thread_count(3)
        assert parallel.thread_count() == 3
    finally:
        parallel.set_thread_count(None)
        parallel.default_thread_count.cache_clear()
    monkeypatch.setattr(parallel, "thread_count", lambda: 2)
    seen, threads = [], set()

    def kernel(a, b):
        threads.add(threading.get_ident())
        inner = []
        parallel.split_run(lambda c, d: inner.append((c, d)), 10, 10**9)  # nested: serial, no deadlock
        seen.append((a, b, inner))

    parallel.split_run(kernel, 9, 10**9)
    assert sorted((a, b) for a, b, _ in seen) == [(0, 4), (4, 9)] and len(threads) == 2
    assert all(inner == [(0, 10)] for _, _, inner in seen)
    parallel.split_run(kernel, 9, 10)  # too little work: one range on the calling thread
    assert seen[-1][:2] == (0, 9)

    def failing(a, b):
        if a > 0:
            raise RuntimeError("range failed")

    with pytest.raises(RuntimeError, match="range failed"):
        parallel.split_run(failing, 4, 10**9)


def test_a_forked_child_gets_a_pool_of_its_own(monkeypatch):
    """After a fork the parent's pool threads are gone; the child's split calls still run (no hang)."""
    import multiprocessing

    from touchreal.preprocess import parallel

    monkeypatch.setattr(parallel, "thread_count", lambda: 2)
    seen = []
    parallel.split_run(lambda a, b: seen.append((a, b)), 4, 10**9)  # the parent's pool exists now
    assert len(seen) == 2

    def child(conn):
        got = []
        parallel.split_run(lambda a, b: got.append((a, b)), 4, 10**9)
        conn.send(sorted(got))

    ctx = multiprocessing.get_context("fork")
    parent, end = ctx.Pipe()
    proc = ctx.Process(target=child, args=(end,))
    proc.start()
    try:
        assert parent.poll(30), "the forked child hung in split_run"
        assert parent.recv() == [(0, 2), (2, 4)]
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
