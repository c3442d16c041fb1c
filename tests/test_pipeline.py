"""One code path: whole-recording and chunk-wise encoding give identical channels and spikes."""

import numpy as np
import pytest

from touchreal.params import EncoderParams, PreprocessParams, default_params
from touchreal.preprocess.gate import calibrate
from touchreal.preprocess.pipeline import Channels, Preprocessor, preprocess_trial, preprocess_trial_windows
from touchreal.raw import RawChunk
from touchreal.sources.replay import ReplaySource
from touchreal.settings import CLASSES
from touchreal.stream import encode_chunks, encode_trial

from helpers import synthetic_trial


def _calibrated(trial) -> EncoderParams:
    p = default_params()
    pre = calibrate([trial.pvdf[trial.pvdf_t < 0.28]], p.preprocess)
    return p.model_copy(update={"preprocess": pre})


def _sample_chunks(trial):
    """Chunks of one sample of either sensor, in time order (how a serial reader delivers them)."""
    events = sorted([(t, 0, i) for i, t in enumerate(trial.st_t)] + [(t, 1, i) for i, t in enumerate(trial.pvdf_t)])
    e = np.zeros(0)
    for t, which, i in events:
        if which == 0:
            yield RawChunk(trial.st_t[i : i + 1], np.float64(trial.st[i : i + 1])[:, None], e, np.zeros((0, 1)))
        else:
            yield RawChunk(e, np.zeros((0, 1)), trial.pvdf_t[i : i + 1], np.float64(trial.pvdf[i : i + 1])[:, None])


def _irregular_chunks(trial, seed=0):
    rng = np.random.default_rng(seed)
    src = ReplaySource(trial)
    while not src.done:
        yield src.read(float(rng.choice([0.0, 0.0004, 0.003, 0.032, 0.1, 0.25])))


def _assert_same(a, b):
    for c in CLASSES:
        np.testing.assert_array_equal(a.train(c), b.train(c))


def test_chunking_does_not_change_channels():
    tr = synthetic_trial()
    params = _calibrated(tr).preprocess
    whole = preprocess_trial(tr, params)
    pre = Preprocessor(params)
    parts = [pre.process(c.st_t, c.st, c.pvdf_t, c.pvdf) for c in _irregular_chunks(tr)] + [pre.finish()]
    got = Channels.concatenate(parts, 1)
    assert got.k0 == whole.k0
    np.testing.assert_array_equal(got.data, whole.data)
    assert np.all(np.isfinite(whole.data))


def test_one_code_path_single_sample_irregular_and_whole():
    tr = synthetic_trial(duration_s=1.2)
    params = _calibrated(tr)
    whole = encode_chunks(params, [ReplaySource(tr).read(10.0)])
    assert all(len(whole.train(c)) > 0 for c in CLASSES), "the synthetic press must drive every class"
    _assert_same(whole, encode_chunks(params, _sample_chunks(tr)))
    _assert_same(whole, encode_chunks(params, _irregular_chunks(tr, seed=3)))
    trains = encode_trial(tr, params, update_s=0.032)
    for c in CLASSES:
        np.testing.assert_array_equal(trains[c], whole.train(c))


@pytest.mark.parametrize("window_ms", [4, 8, 16, 32, 64, 128, 256, 512])
def test_every_window_works_and_sets_the_latency(window_ms):
    tr = synthetic_trial()
    params = PreprocessParams(window_ms=window_ms)
    pre = Preprocessor(params)
    src = ReplaySource(tr)
    head = pre.process(*_fields(src.read(1.0)))
    # after 1 s of input the output reaches 1 s minus the latency (within one STFT hop and PCHIP knot)
    end = head.t0_s + head.n_samples / 5000.0
    assert 1.0 - pre.latency_s(float(window_ms)) - 0.02 <= end <= 1.0 - window_ms / 1000.0 * 0.5 + 1e-9
    ch = Channels.concatenate([head, pre.process(*_fields(src.read(10.0))), pre.finish()], 1)
    assert np.all(np.isfinite(ch.data))
    assert abs(ch.t0_s + ch.n_samples / 5000.0 - tr.st_t[-1]) < 0.01


def _fields(c):
    return c.st_t, c.st, c.pvdf_t, c.pvdf


def test_channels_follow_the_physics():
    tr = synthetic_trial()
    ch = preprocess_trial(tr, _calibrated(tr).preprocess)
    t = ch.t_s
    st, dst = ch.data[:, 0, 0], ch.data[:, 0, 1]
    hold = (t > 0.6) & (t < 0.85)
    assert abs(st[hold].mean() - 3.0) < 0.05  # ST tracks the 3 N hold
    assert dst[(t > 0.3) & (t < 0.45)].max() > 15  # pressing at 30 N/s
    assert dst[(t > 0.9) & (t < 1.1)].min() < -10  # releasing at -20 N/s
    pv = ch.data[:, 0, 2]
    burst = (t > 0.55) & (t < 0.75)
    quiet = (t > 1.2) & (t < 1.4)
    assert pv[burst].std() > 10 * pv[quiet].std()  # vibration kept, mains + noise gated


@pytest.mark.shared
@pytest.mark.parametrize("protocol", ["ramp", "sine"])
def test_rig_trials_identical_whole_update_and_single_samples(rig, protocol):
    entries = rig.entries(protocol)
    params = default_params()
    e = entries[len(entries) // 2]
    tr = rig.load(e)
    whole = encode_chunks(params, [ReplaySource(tr).read(100.0)])
    assert len(whole) > 0
    _assert_same(whole, encode_chunks(params, ReplaySource(tr).chunks(0.032)))
    _assert_same(whole, encode_chunks(params, _sample_chunks(tr)))


def _contact_free(duration_s: float, seed: int = 1):
    """A resting sensor: ST at 0.05 N, PVDF = mains hum (50/150/250 Hz, 17 mV in all) + 2 mV noise."""
    rng = np.random.default_rng(seed)
    st_t = 0.002 + np.arange(int(duration_s * 100)) / 100.0
    pv_t = 0.0001 + np.arange(int(duration_s * 2000)) / 2000.0
    hum = 0.010 * np.sin(2 * np.pi * 50 * pv_t + 0.7) + 0.005 * np.sin(2 * np.pi * 150 * pv_t - 1.2) + 0.002 * np.sin(2 * np.pi * 250 * pv_t)
    pv = hum + rng.normal(0, 0.002, pv_t.size)
    return st_t, np.full((st_t.size, 1), 0.05), pv_t, pv[:, None]


def test_stream_start_has_no_notch_ringing():
    """The PVDF filters start primed with the hum of the first 100 ms: the notched PVDF channel and
    its derivative are as quiet at stream start as a second later (cold notches let about half the
    hum through for the first 0.1 s: dPVDF 5x its resting level)."""
    st_t, st, pv_t, pv = _contact_free(1.5)
    params = PreprocessParams(notch_harmonics=[1, 3, 5], gate=None)
    pre = Preprocessor(params)
    ch = Channels.concatenate([pre.process(st_t, st, pv_t, pv), pre.finish()], 1)
    t = ch.t_s
    early, late = t < ch.t0_s + 0.05, (t > 1.0) & (t < 1.4)
    for j in (2, 3):  # PVDF, dPVDF
        x = ch.data[:, 0, j]
        assert x[early].std() < 1.3 * x[late].std()


def test_stream_shorter_than_the_hum_estimate_still_flushes():
    st_t, st, pv_t, pv = _contact_free(0.06)
    pre = Preprocessor(PreprocessParams())
    assert pre.process(st_t, st, pv_t, pv).n_samples == 0  # PVDF held for the hum estimate
    assert "pv_held" in pre.state_arrays()
    ch = pre.finish()
    assert ch.n_samples > 0 and np.all(np.isfinite(ch.data))
    assert "pv_held" not in pre.state_arrays()


def test_several_windows_at_once_equal_one_window_each():
    tr = synthetic_trial(duration_s=1.2)
    params = _calibrated(tr).preprocess
    both = preprocess_trial_windows(tr, params, [16.0, None, 128.0])
    for w in (16.0, 128.0):
        one = preprocess_trial(tr, params.model_copy(update={"window_ms": w}))
        assert both[w].k0 == one.k0
        np.testing.assert_array_equal(both[w].data, one.data)
    st_only = both[None]
    assert st_only.k0 == both[128.0].k0 and st_only.n_samples == both[128.0].n_samples
    np.testing.assert_array_equal(st_only.data[:, :, :2], both[128.0].data[:, :, :2])
    assert not st_only.data[:, :, 2:].any()


def test_a_preprocessor_on_a_shared_acquisition_is_fed_through_it():
    from touchreal.preprocess.pipeline import Acquisition

    acq = Acquisition(n_taxels=3)
    pre = Preprocessor(PreprocessParams(), acquisition=acq, taxels=range(1, 3))
    assert pre.n_taxels == 2
    with pytest.raises(RuntimeError, match="consume"):
        pre.feed(np.array([0.0]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="contiguous block"):
        Preprocessor(PreprocessParams(), acquisition=acq, taxels=range(2, 4))


def test_gathered_preprocessors_continue_their_taxels():
    """Preprocessors over taxel subsets of one acquisition (every source), gathered (reordered) into one
    mid-stream, continue as the parts would have: the channels of a preprocessor that ran every taxel
    all along, to rounding (a batch of another size may round the FFTs differently: ~1e-15 of the range)."""
    from touchreal.preprocess.pipeline import Acquisition

    trial = synthetic_trial(duration_s=1.5, seed=3)
    n = 5
    st = np.float64(trial.st)[:, None] * np.linspace(0.5, 1.5, n)[None, :]
    pv = np.float64(trial.pvdf)[:, None] * np.linspace(1.5, 0.5, n)[None, :]
    sources = [None, 16.0, 128.0]
    acq = Acquisition(n, 128.0)
    whole = Preprocessor(PreprocessParams(), sources=sources, acquisition=acq, taxels=range(n))
    a = Preprocessor(PreprocessParams(), sources=sources, acquisition=acq, taxels=np.array([3, 1]))
    b = Preprocessor(PreprocessParams(), sources=sources, acquisition=acq, taxels=np.array([0, 4, 2]))
    out = {s: [] for s in sources}
    merged = None
    for t0 in np.arange(0.0, 1.5, 0.005):
        si = (trial.st_t >= t0) & (trial.st_t < t0 + 0.005)
        pi = (trial.pvdf_t >= t0) & (trial.pvdf_t < t0 + 0.005)
        new = acq.push(trial.st_t[si], st[si], trial.pvdf_t[pi], pv[pi])
        for pre in (whole, a, b) if merged is None else (whole, merged):
            pre.consume(*new)
        for s in sources:
            ref = whole.take(s)
            parts = [a.take(s), b.take(s)] if merged is None else [merged.take(s)]
            out[s].append((ref, parts))
        if merged is None and t0 >= 0.6:  # a's taxel 1, then all of b's, then a's taxel 3
            merged = Preprocessor.gather([(a, np.array([1])), (b, np.arange(3))])
            assert merged.taxels.tolist() == [1, 0, 4, 2] and merged.cursor == a.cursor
    for s in sources:
        for ref, parts in out[s]:
            cols = [a.taxels, b.taxels] if len(parts) == 2 else [merged.taxels]
            for ch, taxels in zip(parts, cols):
                assert ch.k0 == ref.k0 and ch.n_samples == ref.n_samples
                scale = 1.0 + np.abs(ref.data).max(axis=(0, 1), initial=0.0)  # per channel
                assert (np.abs(ch.data - ref.data[:, taxels]) <= 1e-12 * scale).all()
    assert sum(ref.n_samples for ref, _ in out[None]) > 6000
