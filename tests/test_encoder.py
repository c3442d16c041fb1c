import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from touchreal.encoding.encoder import Encoder, InputStage, channel_currents, encode_population, rectify
from touchreal.encoding.lif import REFRACTORY_SAMPLES, LifPopulation
from touchreal.params import ClassParams, default_params
from touchreal.preprocess.pipeline import Channels
from touchreal.settings import CLASSES


def _channels(t=4000, taxels=1, seed=0):
    rng = np.random.default_rng(seed)
    tt = np.arange(t) / 5000.0
    st = 2 + 2 * np.sin(2 * np.pi * 2 * tt)
    base = np.stack([st, 8 * np.pi * np.cos(2 * np.pi * 2 * tt), 0.1 * np.sin(2 * np.pi * 150 * tt), 94 * np.cos(2 * np.pi * 150 * tt)], 1)
    return base[:, None, :] * rng.uniform(0.5, 1.5, (1, taxels, 1))


def test_rectify_order_and_channel_decomposition():
    x = np.array([[1.0, -2.0, 3.0, -4.0]])
    np.testing.assert_array_equal(rectify(x), [[1, 0, 0, 2, 3, 0, 0, 4]])
    cp = ClassParams(weights=[1, 2, 3, 4, 5, 6, 7, 8], i_sat=0, tau_ms=10, ih=[0, 0], delay_ms=0)
    cur = channel_currents(_channels()[:, 0], cp)
    total = rectify(_channels()[:, 0]) @ np.array(cp.weights, float)
    np.testing.assert_allclose(cur.sum(axis=1), total)  # eq. 11: additive before saturation


def test_encoder_matches_population_api_and_delay_shifts():
    p = default_params()
    ch = _channels()
    ev = Encoder(p).process(Channels(1000, ch))
    pop = encode_population(ch[:, 0], 1000 / 5000.0, [p.classes[c] for c in CLASSES])
    for c, train in zip(CLASSES, pop):
        np.testing.assert_allclose(ev.train(c), train)
        assert train.size > 0
    shifted = p.classes["SA1"].model_copy(update={"delay_ms": p.classes["SA1"].delay_ms + 7.5})
    np.testing.assert_allclose(encode_population(ch[:, 0], 0.2, [shifted])[0], pop[0] + 0.0075, rtol=0, atol=1e-12)


def test_taxels_are_independent_and_classes_subset():
    p = default_params()
    ch = _channels(taxels=5, seed=1)
    ev = Encoder(p, n_taxels=5).process(Channels(0, ch))
    for j in range(5):
        single = Encoder(p).process(Channels(0, ch[:, j : j + 1]))
        for c in CLASSES:
            np.testing.assert_array_equal(ev.train(c, j), single.train(c))
    only_pc = Encoder(p, n_taxels=5, classes=["PC"])
    assert only_pc.lif.n_neurons == 5
    out = only_pc.process(Channels(0, ch))
    assert set(out.cls.tolist()) == {CLASSES.index("PC")}
    assert np.all(np.diff(ev.t_s) >= 0)
    with pytest.raises(ValueError, match="no class"):
        Encoder(p.model_copy(update={"classes": {"SA1": p.classes["SA1"]}}), classes=["RA"])


@settings(max_examples=40, deadline=None)
@given(level=st.floats(0.0, 2.0), cuts=st.lists(st.integers(0, 300), max_size=8))
def test_lif_chunk_invariance_and_refractory(level, cuts):
    rng = np.random.default_rng(0)
    current = level * rng.uniform(0, 1, (1200, 3))
    ih = np.array([[-0.5] * 10 + [0.0] * 5] * 3)
    whole = LifPopulation(np.array([5.0, 20.0, 100.0]), ih)
    k, n = whole.step(current)
    lif = LifPopulation(np.array([5.0, 20.0, 100.0]), ih)
    edges = sorted(set([0, 1200] + [c * 4 for c in cuts if c * 4 < 1200]))
    got = [(lambda kk, nn, a=a: (kk + a, nn))(*lif.step(current[a:b])) for a, b in zip(edges, edges[1:])]
    np.testing.assert_array_equal(np.concatenate([g[0] for g in got]), k)
    np.testing.assert_array_equal(np.concatenate([g[1] for g in got]), n)
    for j in range(3):
        assert np.all(np.diff(k[n == j]) > REFRACTORY_SAMPLES)


def test_lif_constant_current_rate_matches_closed_form():
    # no post-spike current: V_k = I * tau * (1 - (1 - 1/tau)^k); first k with V > 1 is the period
    tau, i = 50.0, 0.05
    lif = LifPopulation(np.array([tau]), np.zeros((1, 190)))
    k, _ = lif.step(np.full((5000, 1), i))
    period = int(np.ceil(np.log(1 - 1 / (i * tau)) / np.log(1 - 1 / tau)))
    assert np.all(np.diff(k) == period)


def input_current(channels, params):
    """(T, X, 4) -> (T, X) current of one class on every taxel, from a fresh input stage."""
    n_x = channels.shape[1]
    return InputStage([params] * n_x, np.arange(n_x)).process(channels)


def _cp(w, **kw):
    return ClassParams(**{"weights": list(w), "i_sat": 0.0, "tau_ms": 10.0, "ih": [0.0, 0.0], "delay_ms": 0.0, **kw})


def test_input_current_matches_rectified_weights_and_saturates():
    rng = np.random.default_rng(5)
    ch = rng.normal(0, 3, (50, 3, 4))
    w = rng.normal(0, 1, 8)
    raw = rectify(ch) @ w  # (50, 3)
    np.testing.assert_allclose(input_current(ch, _cp(w)), raw, rtol=1e-12)
    sat = input_current(ch, _cp(w, i_sat=5.0))
    np.testing.assert_allclose(sat, 5.0 * raw / (5.0 + np.abs(raw)), rtol=1e-12)
    huge = input_current(np.full((1, 1, 4), 1e300), _cp(np.ones(8), i_sat=5.0))
    assert np.isfinite(huge).all() and abs(huge[0, 0]) <= 5.0


def test_class_lowpass_is_a_butterworth_before_rectification():
    ch = _channels(t=3000, taxels=2)
    w = np.array([0.3, 0.1, 0.01, 0.02, 5.0, 4.0, 0.02, 0.01])
    cur = input_current(ch, _cp(w, lowpass_hz=120.0))
    sos = signal.butter(3, 120.0, fs=5000.0, output="sos")
    zi = signal.sosfilt_zi(sos)[:, :, None, None] * ch[0][None, None]  # steady state at the first sample
    filt, _ = signal.sosfilt(sos, ch, axis=0, zi=zi)
    np.testing.assert_allclose(cur, rectify(filt) @ w, rtol=1e-9, atol=1e-12)
    # 3rd order at 120 Hz: the 150 Hz PVDF component is attenuated to |H(150 Hz)| ~ 0.46
    plain = input_current(ch, _cp([0, 0, 0, 0, 1, 1, 0, 0]))
    lp = input_current(ch, _cp([0, 0, 0, 0, 1, 1, 0, 0], lowpass_hz=120.0))
    assert 0.4 < lp[1000:].max() / plain[1000:].max() < 0.55


def test_negative_lead_delays_positive_parts_only():
    rng = np.random.default_rng(2)
    ch = rng.normal(0, 1, (400, 2, 4))
    w = rng.uniform(0.1, 1, 8)
    cur = input_current(ch, _cp(w, negative_lead_ms=2.0))  # 10 samples
    pos = np.maximum(ch, 0) @ w[0::2]
    neg = np.maximum(-ch, 0) @ w[1::2]
    delayed = np.concatenate([np.repeat(pos[:1], 10, axis=0), pos[:-10]])  # history = first sample
    np.testing.assert_allclose(cur, delayed + neg, rtol=1e-12)


def test_class_highpass_follows_the_lowpass_and_removes_a_steady_baseline():
    ch = _channels(t=3000, taxels=2) + np.array([0.5, 0.0, 0.03, 0.0])  # a baseline offset on ST and PVDF
    w = np.array([0.3, 0.1, 0.01, 0.02, 5.0, 4.0, 0.02, 0.01])
    cur = input_current(ch, _cp(w, lowpass_hz=120.0, highpass_hz=5.0))
    sos = np.vstack([signal.butter(3, 120.0, fs=5000.0, output="sos"), signal.butter(1, 5.0, btype="high", fs=5000.0, output="sos")])
    zi = signal.sosfilt_zi(sos)[:, :, None, None] * ch[0][None, None]  # steady state at the first sample
    filt, _ = signal.sosfilt(sos, ch, axis=0, zi=zi)
    np.testing.assert_allclose(cur, rectify(filt) @ w, rtol=1e-9, atol=1e-12)
    steady = np.ones((2000, 1, 4)) * np.array([0.5, -2.0, 0.03, -40.0])
    assert np.abs(input_current(steady, _cp(w, highpass_hz=5.0))).max() < 1e-12  # a baseline drives nothing
    assert input_current(steady, _cp(w))[0, 0] > 0.1  # without the high-pass it does
    step = steady.copy()
    step[1000:, 0, 2] += 0.1  # a PVDF transient passes: 1st order at 5 Hz keeps e^-(2 pi 5 t) of a step
    got = input_current(step, _cp([0, 0, 0, 0, 1, 1, 0, 0], highpass_hz=5.0))[:, 0]
    assert got[1000] == pytest.approx(0.1, rel=0.01) and got[1000 + 159] == pytest.approx(0.1 * np.exp(-2 * np.pi * 5 * 0.0318), rel=0.02)


def test_a_column_without_highpass_keeps_its_bits_beside_one_with_it():
    ch = _channels(t=2000, taxels=2, seed=8)
    lp = _cp([0.3, 0.1, 0.01, 0.02, 5.0, 4.0, 0.02, 0.01], lowpass_hz=300.0)
    alone = InputStage([lp, _cp(lp.weights)], [0, 1]).process(ch)
    mixed = InputStage([lp, _cp(lp.weights), lp.model_copy(update={"highpass_hz": 5.0})], [0, 1, 1]).process(ch)
    np.testing.assert_array_equal(mixed[:, :2], alone)  # the identity section adds nothing, bit for bit


@settings(max_examples=25, deadline=None)
@given(cuts=st.lists(st.integers(1, 599), max_size=6), lead=st.floats(0.0, 20.0), hp=st.sampled_from([None, 0.5, 40.0]))
def test_class_input_chunk_invariance(cuts, lead, hp):
    ch = _channels(t=600, taxels=3, seed=4)
    p = _cp([0.3, 0.1, 0.01, 0.02, 5.0, 4.0, 0.02, 0.01], i_sat=3.0, lowpass_hz=90.0, negative_lead_ms=lead, highpass_hz=hp)
    whole = input_current(ch, p)
    inp = InputStage([p] * 3, [0, 1, 2])
    edges = sorted({0, 600, *cuts})
    parts = np.concatenate([inp.process(ch[a:b]) for a, b in zip(edges, edges[1:])])
    np.testing.assert_array_equal(parts, whole)


def test_bad_parameters_rejected():
    with pytest.raises(ValueError, match="tau"):
        LifPopulation(np.array([0.5]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        LifPopulation(np.array([5.0]), np.full((1, 3), np.nan))


def test_class_lowpass_on_dpvdf_gives_a_band_pass():
    # equal PVDF amplitude at every frequency (the sine protocol's matched drive): dPVDF grows with f,
    # the 3rd-order low-pass cuts above its cutoff, so a dPVDF-driven unit is tuned near the cutoff
    t = np.arange(5000) / 5000.0
    rates = {}
    for f in (10.0, 100.0, 400.0):
        ch = np.zeros((t.size, 4))
        ch[:, 2] = 0.15 * np.sin(2 * np.pi * f * t)
        ch[:, 3] = 0.15 * 2 * np.pi * f * np.cos(2 * np.pi * f * t)
        cp = _cp([0, 0, 0, 0, 0, 0, 0.01, 0.01], tau_ms=6.0, ih=[-2.0, 0.0], lowpass_hz=100.0)
        rates[f] = encode_population(ch, 0.0, [cp])[0].size
        flat = encode_population(ch, 0.0, [cp.model_copy(update={"lowpass_hz": None})])[0].size
        assert flat >= rates[f]  # the filter only removes drive
    assert rates[100.0] > 2 * rates[10.0] and rates[100.0] > 2 * rates[400.0]


def test_encoder_with_input_stage_is_chunk_invariant_and_reports_its_state():
    p = default_params()
    classes = dict(p.classes)
    classes["SA1"] = classes["SA1"].model_copy(update={"lowpass_hz": None, "negative_lead_ms": 0.0})
    classes["RA"] = classes["RA"].model_copy(update={"lowpass_hz": 120.0, "negative_lead_ms": 6.0})
    classes["PC"] = classes["PC"].model_copy(update={"lowpass_hz": 400.0, "negative_lead_ms": 0.0})
    p = p.model_copy(update={"classes": classes})
    ch = _channels(t=3000, taxels=3, seed=2)
    whole = Encoder(p, n_taxels=3).process(Channels(0, ch))
    enc = Encoder(p, n_taxels=3)
    parts = [enc.process(Channels(a, ch[a:b])) for a, b in ((0, 7), (7, 1000), (1000, 1001), (1001, 3000))]
    got = type(whole).concatenate(parts)
    for c in CLASSES:
        for x in range(3):
            np.testing.assert_array_equal(got.train(c, x), whole.train(c, x))
    state = enc.state_arrays()
    assert state["input_lowpass"].shape[0] == 2 * 3  # RA and PC columns of 3 taxels
    assert state["input_lead"].shape == (9, 30)  # 6 ms = 30 samples, one row per column
    assert all(np.isfinite(a).all() for a in state.values())


def test_input_stage_rejects_channels_of_the_wrong_shape():
    p = ClassParams(weights=[1.0] * 8, i_sat=0.0, tau_ms=1.0, ih=[0.0, 0.0], delay_ms=0.0, lowpass_hz=100.0)
    stage = InputStage([p, p], [0, 1])
    for bad in (np.zeros((10, 2, 3)), np.zeros((10, 1, 4)), np.zeros((10, 4))):
        with pytest.raises(ValueError, match="channels must be"):
            stage.process(bad)
    assert stage.process(np.ones((10, 2, 4))).shape == (10, 2)


def test_set_columns_keeps_continuing_columns_and_starts_new_ones_from_rest():
    p = default_params()
    ch = _channels(t=4000, taxels=3, seed=6)
    enc = Encoder(p, n_taxels=3)
    parts = [enc.process(Channels(0, ch[:1000]))]
    enc.set_columns({"PC": [0, 2], "RA": [1]})
    assert enc.columns == [(0, "PC"), (1, "RA"), (2, "PC")]
    parts.append(enc.process(Channels(1000, ch[1000:2500])))
    enc.set_columns({"PC": [0], "SA1": [1, 2], "RA": [1]})
    parts.append(enc.process(Channels(2500, ch[2500:])))
    got = type(parts[0]).concatenate(parts)
    whole = Encoder(p, n_taxels=3).process(Channels(0, ch))
    for c, x in (("PC", 0), ("RA", 1)):  # active all along: bit-identical to the full encoder
        np.testing.assert_array_equal(got.train(c, x), whole.train(c, x))
    # SA1 on taxel 2 restarted at sample 2500 from rest: as a fresh encoder started there
    fresh = Encoder(p, n_taxels=3, classes=["SA1"]).process(Channels(2500, ch[2500:]))
    np.testing.assert_array_equal(got.train("SA1", 2), np.concatenate([whole.train("SA1", 2)[whole.train("SA1", 2) < 0.2], fresh.train("SA1", 2)]))
    assert got.train("PC", 2).max() < 0.5 + p.classes["PC"].delay_ms / 1000 + 1e-9  # PC on taxel 2 stopped at sample 2500
    with pytest.raises(ValueError, match="out of range"):
        enc.set_columns({"PC": [3]})


def test_gathered_encoders_continue_their_columns_bit_for_bit():
    """Two encoders over taxel subsets, gathered (reordered) into one mid-stream: every column they ran
    continues bit for bit (the whole encoder's spikes on those taxels); a column neither ran starts from rest."""
    p = default_params()
    ch = _channels(t=4000, taxels=5, seed=7)
    whole = Encoder(p, n_taxels=5).process(Channels(0, ch))
    a, b = Encoder(p, n_taxels=2), Encoder(p, n_taxels=3, columns={"SA1": [0, 1, 2], "RA": [2]})
    cols_a, cols_b = [3, 1], [0, 4, 2]  # the taxels each one runs
    first = [a.process(Channels(0, ch[:1500, cols_a])), b.process(Channels(0, ch[:1500, cols_b]))]
    g = Encoder.gather([(b, np.array([2, 0])), (a, np.array([0, 1]))], {"SA1": [0, 1, 2, 3], "RA": [0, 2, 3], "PC": [2]})
    taxels = [cols_b[2], cols_b[0], cols_a[0], cols_a[1]]  # the gathered encoder's taxels: 2, 0, 3, 1
    assert g.n_taxels == 4 and g.columns == [(0, "SA1"), (0, "RA"), (1, "SA1"), (2, "SA1"), (2, "RA"), (2, "PC"), (3, "SA1"), (3, "RA")]
    later = g.process(Channels(1500, ch[1500:, taxels]))
    for local, x in enumerate(taxels):
        ran = [c for c in CLASSES if (local, c) in g.columns]
        for c in ran:
            before = [e.train(c, cols.index(x)) for e, cols in zip(first, (cols_a, cols_b)) if x in cols]
            got = np.concatenate(before + [later.train(c, local)])
            if (c, x) == ("RA", 0):  # neither part ran it: started at the gather, from rest
                fresh = Encoder(p, n_taxels=1, classes=[c]).process(Channels(1500, ch[1500:, [x]]))
                np.testing.assert_array_equal(later.train(c, local), fresh.train(c))
            else:
                np.testing.assert_array_equal(got, whole.train(c, x))


def test_set_columns_carries_state_between_stages_with_and_without_a_highpass_section():
    p = default_params()
    classes = dict(p.classes)
    classes["PC"] = classes["PC"].model_copy(update={"highpass_hz": 5.0})
    p = p.model_copy(update={"classes": classes, "version": 4})
    ch = _channels(t=3000, taxels=2, seed=9)
    enc = Encoder(p, n_taxels=2)
    parts = [enc.process(Channels(0, ch[:1000]))]
    enc.set_columns({"RA": [0]})  # no high-pass column left: the stage drops its section
    parts.append(enc.process(Channels(1000, ch[1000:2000])))
    enc.set_columns({"RA": [0], "PC": [1]})  # and takes it up again
    parts.append(enc.process(Channels(2000, ch[2000:])))
    got = type(parts[0]).concatenate(parts)
    whole = Encoder(p, n_taxels=2).process(Channels(0, ch))
    np.testing.assert_array_equal(got.train("RA", 0), whole.train("RA", 0))  # active all along
    assert whole.train("RA", 0).size > 10


def test_fused_kernel_equals_input_stage_then_lif_across_tiles_layouts_and_threads(monkeypatch):
    """The encoder's fused kernel (input stage + LIF, taxel tiles, both cores) gives exactly the spikes
    of the separate input current fed to :class:`LifPopulation`, for columns spread over several
    tiles in any order, channels in a transposed memory layout, and ranges split over threads."""
    from touchreal.preprocess import parallel

    p = default_params()
    classes = dict(p.classes)
    classes["SA1"] = classes["SA1"].model_copy(update={"negative_lead_ms": 3.0, "lowpass_hz": 80.0})
    cps = [classes[c] for c in CLASSES]
    n_x = 37  # three tiles, the last one partial
    taxels = np.random.default_rng(3).permutation(np.repeat(np.arange(n_x), 3))  # unsorted: tiles reloaded
    cols = [cps[i % 3] for i in range(taxels.size)]
    ch = _channels(t=2500, taxels=n_x, seed=4) * np.random.default_rng(5).uniform(0.3, 3.0, (1, n_x, 4))
    transposed = np.ascontiguousarray(ch.transpose(0, 2, 1)).transpose(0, 2, 1)  # (T, X, 4) view of (T, 4, X)
    ref_in = InputStage(cols, taxels)
    tau = np.array([c.tau_samples for c in cols])
    ih = np.array([c.ih for c in cols]) @ np.array([[1.0] * 190, [0.5] * 190])
    ref_lif = LifPopulation(tau, ih)
    want = [ref_lif.step(ref_in.process(ch[a:b])) for a, b in ((0, 900), (900, 2500))]
    assert sum(k.size for k, _ in want) > 500
    for threads, data in ((1, ch), (2, transposed)):
        monkeypatch.setattr(parallel, "thread_count", lambda threads=threads: threads)
        monkeypatch.setattr(parallel, "WORK_SCALE", 0.0)  # every call with more than one column splits
        fused_in, fused_lif = InputStage(cols, taxels), LifPopulation(tau, ih)
        for (a, b), (k, n) in zip(((0, 900), (900, 2500)), want):
            got_k, got_n = fused_in.spikes(data[a:b], fused_lif)
            np.testing.assert_array_equal(got_k, k)
            np.testing.assert_array_equal(got_n, n)
        np.testing.assert_array_equal(fused_lif.state.v, ref_lif.state.v)
        np.testing.assert_array_equal(fused_in.zi, ref_in.zi)
        np.testing.assert_array_equal(fused_in.ring, ref_in.ring)
