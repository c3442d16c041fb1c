"""The stream's mains frequency: resolved once from its first 0.1 s of PVDF, so a parameter set
fitted on 50 Hz mains notches a 60 Hz source's hum (and the other way round)."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.params import PreprocessParams, default_params
from touchreal.preprocess.mains import resolve_mains
from touchreal.preprocess.pipeline import Channels, Preprocessor
from touchreal.raw import RawChunk
from touchreal.stream import StreamEncoder

FS = 2000.0


def _pvdf(seconds: float, n_taxels: int, mains_hz: float | None, seed: int = 0, hum_v: float = 0.01,
          noise_v: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """(t, PVDF (n, N)): Gaussian noise plus, with ``mains_hz``, a hum with odd harmonics 1-9 whose
    amplitude and phase differ per taxel (a film's pickup)."""
    rng = np.random.default_rng(seed)
    t = 0.0001 + np.arange(int(round(seconds * FS))) / FS
    x = rng.normal(0.0, noise_v, (t.size, n_taxels))
    if mains_hz is not None:
        for h, amp in ((1, 1.0), (3, 0.5), (5, 0.3), (7, 0.2), (9, 0.1)):
            gain = hum_v * amp * rng.uniform(0.5, 1.5, n_taxels)
            x += gain * np.sin(2 * np.pi * h * mains_hz * t[:, None] + rng.uniform(0, 2 * np.pi, n_taxels))
    return t, x


@pytest.mark.parametrize("configured", [50.0, 60.0])
@pytest.mark.parametrize("actual", [50.0, 60.0])
def test_the_hum_decides_whatever_frequency_the_parameters_name(configured, actual):
    params = PreprocessParams(mains_hz=configured)
    for seed in range(5):
        _, x = _pvdf(0.1, 4, actual, seed=seed, hum_v=0.003)  # hum 1.5x the noise rms at the fundamental
        assert resolve_mains(x, params, FS) == actual


def test_noise_and_contact_keep_the_configured_frequency():
    """Without hum (noise alone, or noise under a press transient and a 40, 55 or 300 Hz vibration,
    300 Hz being a harmonic of 60 Hz) the choice stays with the parameters in 200 of 200 draws."""
    params = PreprocessParams(mains_hz=50.0)
    t = 0.0001 + np.arange(200) / FS
    for seed in range(200):
        rng = np.random.default_rng(seed)
        _, x = _pvdf(0.1, 3, None, seed=seed)
        if seed % 2:
            x += 0.05 * np.exp(-((t - 0.04) / 0.01) ** 2)[:, None]  # the film's press transient
            x += rng.choice([0.02, 1.6]) * np.sin(2 * np.pi * rng.choice([40.0, 55.0, 300.0]) * t + rng.uniform(0, 6))[:, None]
        assert resolve_mains(x, params, FS) == 50.0


def test_an_empty_candidate_list_or_no_notches_keep_the_configured_frequency():
    _, x = _pvdf(0.1, 2, 60.0)
    assert resolve_mains(x, PreprocessParams(mains_hz=50.0, mains_candidates_hz=[]), FS) == 50.0
    assert resolve_mains(x, PreprocessParams(mains_hz=50.0, notch_harmonics=[]), FS) == 50.0
    assert resolve_mains(x[:3], PreprocessParams(mains_hz=50.0), FS) == 50.0  # too short to fit the lines


def _hum_left(params: PreprocessParams, seconds: float = 1.0, chunk: int | None = None
              ) -> tuple[float, Preprocessor, Channels]:
    """(RMS (V) of the PVDF channel from 0.3 s on, the preprocessor, its channels) for a resting
    sensor on 60 Hz mains, fed in chunks of ``chunk`` PVDF samples (default: whole)."""
    t, x = _pvdf(seconds, 2, 60.0, noise_v=0.0005)
    st_t = 0.002 + np.arange(int(seconds * 100)) / 100.0
    st = np.full((st_t.size, 2), 0.05)
    pre = Preprocessor(params, n_taxels=2)
    step = chunk or t.size
    parts = []
    for a in range(0, t.size, step):
        b = min(a + step, t.size)
        sel = (st_t > (t[a - 1] if a else -np.inf)) & (st_t <= t[b - 1])  # the SingleTact samples up to this chunk's end
        pre.feed(st_t[sel], st[sel], t[a:b], x[a:b])
        parts.append(pre.take(params.window_ms))
    pre.flush()
    parts.append(pre.take(params.window_ms))
    ch = Channels.concatenate(parts, 2)
    pv = ch.data[ch.t_s > 0.3, :, 2]
    return float(np.sqrt(np.mean(pv**2))), pre, ch


def test_a_60_hz_source_is_notched_with_parameters_fitted_on_50_hz():
    params = PreprocessParams(mains_hz=50.0, notch_harmonics=[1, 3, 5, 7, 9], gate=None)
    left, pre, _ = _hum_left(params)
    assert pre.acq.mains.hz == 60.0
    fixed, pre_fixed, _ = _hum_left(params.model_copy(update={"mains_candidates_hz": []}))
    assert pre_fixed.acq.mains.hz == 50.0
    assert left < 0.1 * fixed  # the 60 Hz lines notched: 0.4 mV left against the 10 mV the 50 Hz notches leave


def test_the_resolution_does_not_depend_on_the_chunking():
    params = PreprocessParams(mains_hz=50.0, notch_harmonics=[1, 3, 5], gate=None)
    _, _, whole = _hum_left(params)
    _, pre, chunked = _hum_left(params, chunk=7)
    assert pre.acq.mains.hz == 60.0
    assert whole.k0 == chunked.k0
    np.testing.assert_array_equal(whole.data, chunked.data)


def _notched_hz(sos: np.ndarray) -> set[float]:
    """The frequencies (Hz, rounded) of a cascade's zeros on the unit circle below Nyquist (its
    notches; the low-pass's zeros sit at Nyquist)."""
    zeros = np.concatenate([np.roots(sec[:3]) for sec in sos])
    hz = {round(abs(float(np.angle(z))) * FS / (2 * np.pi)) for z in zeros if abs(abs(z) - 1) < 1e-6}
    return {f for f in hz if f < FS / 2}


def test_every_taxel_block_and_a_restarted_branch_use_the_streams_frequency():
    """A stream encoder in blocks resolves once: every block's PVDF filter, also one rebuilt from the
    raw history after its branches stopped, notches 60 Hz and its odd harmonics, not 50 Hz."""
    params = default_params()
    n = 4
    t, x = _pvdf(1.0, n, 60.0)
    se = StreamEncoder(params, n, taxel_block=2)
    assert se.mains_hz is None
    se.set_active({c: range(n) for c in se.classes})
    hop = 10
    for i in range(0, t.size, hop):
        k = i // hop
        st_t = np.array([t[i]]) if k % 2 == 0 else np.zeros(0)
        se.process(RawChunk(st_t, np.full((st_t.size, n), 0.05), t[i : i + hop], x[i : i + hop]))
        if k == 40:
            se.set_active({})
        if k == 60:
            se.set_active({c: range(n) for c in se.classes})  # the branches restart from the raw history
    assert se.mains_hz == 60.0
    harmonics = params.preprocess.notch_harmonics
    for b in se.blocks:
        assert _notched_hz(b.pre.pv_filter.filt.sos) == {60 * h for h in harmonics if 60 * h < 0.49 * FS}
