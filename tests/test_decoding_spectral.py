"""The spectral texture decoder: SA1 + RA + PC counts in 1 ms bins, line spectra inside the graph.

Its features separate a train's temporal frequency from its rate, the exported graph equals the
numpy features, and the streaming decoder gives the offline windows' outputs for three classes in
1 ms bins."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest
from touchreal_client.features import CLASSES

from touchreal.decoding.export import to_onnx
from touchreal.decoding.features import SPECTRUM_HZ, FeatureSpec
from touchreal.decoding.model import load_model, write_model
from touchreal.decoding.plan import ModelSpec, spec_from_meta
from touchreal.decoding.streaming import StreamingDecoder
from touchreal.decoding.train import feature_spec, fit_pipeline, metadata, windows
from touchreal.decoding.windows import encode
from touchreal.params import default_params
from touchreal.simulator.simulate import simulate_dataset

FREQS = np.arange(SPECTRUM_HZ[0], SPECTRUM_HZ[1] + SPECTRUM_HZ[2] / 2, SPECTRUM_HZ[2])


def test_spectrum_finds_the_frequency_whatever_the_rate_and_the_graph_agrees():
    fs = FeatureSpec("spectral", 200, 3, 1.0, 200.0)
    x = np.zeros((4, 200, 3), np.float32)
    x[0, ::50, 1] = 1  # 20 Hz, one spike per cycle
    x[1, ::50, 1] = 3  # 20 Hz, three per cycle: same spectrum after normalisation
    x[2, ::40, 1] = 1  # 25 Hz
    x[3, :, 2] = np.random.default_rng(0).poisson(0.05, 200)  # irregular PC, SA1 and RA silent
    f = fs.transform(x)
    nf = FREQS.size
    ra = f[:, 3 + nf: 3 + 2 * nf]
    assert f[:, :3].tolist()[:3] == [[0, 4, 0], [0, 12, 0], [0, 5, 0]]
    assert FREQS[np.argmax(ra[0, :30])] == 20 and FREQS[np.argmax(ra[2, :30])] == 25
    np.testing.assert_allclose(ra[0], ra[1], rtol=1e-5, atol=1e-6)
    assert np.all(f[3, 3: 3 + 2 * nf] == 0)  # silent classes: zero spectrum, no division by zero
    sess = ort.InferenceSession(fs.graph(17, 8).SerializeToString(), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(sess.run(None, {"counts": x})[0], f, rtol=1e-4, atol=1e-4)
    assert len(fs.names()) == f.shape[1] == 3 + 3 * nf


@pytest.fixture(scope="module")
def fine(tmp_path_factory):
    ds = simulate_dataset("texture-fine", tmp_path_factory.mktemp("fine"), trials=10, seed=8, reference=False)
    p = default_params()
    return [encode(e, ds.load(e), p) for e in ds.trials]


def test_trained_spectral_model_streams_the_offline_outputs(fine, tmp_path):
    spec = ModelSpec("texture_spectral", "texture", ("SA1", "RA", "PC"), 100.0, "spectral", bin_ms=1.0)
    fs = feature_spec(spec)
    counts, labels, groups, _, _ = windows(spec, fine[:8])
    assert counts.shape[1:] == (100, 3) and counts[..., :2].sum() > 0  # SA1 and RA read too
    pipe = fit_pipeline(spec, fs.transform(counts), labels, groups, seed=0)
    meta = metadata(spec, fs, pipe, default_params(), {"dataset": "synthetic", "protocol": "texture"})
    model = load_model(write_model(tmp_path, to_onnx(pipe, fs, meta), meta))
    assert model.meta["bin_ms"] == 1.0 and model.meta["classes"] == ["SA1", "RA", "PC"]
    assert spec_from_meta(model.meta) == spec
    tr = fine[9]
    held, _, _, steps, _ = windows(spec, [tr])
    expected = model.run(model.session(1), held)[0]
    np.testing.assert_allclose(expected, pipe.predict_proba(fs.transform(held)), atol=1e-4)
    t = np.concatenate([tr.spikes_us[c] for c in CLASSES])
    cls = np.concatenate([np.full(tr.spikes_us[c].size, i) for i, c in enumerate(CLASSES)])
    o = np.argsort(t, kind="stable")
    t, cls = t[o].astype(np.uint64), cls[o]
    bounds = np.concatenate(([0], np.cumsum(np.random.default_rng(3).integers(1_000, 70_000, 200))))
    bounds = bounds[bounds < int(tr.entry["stim_end_s"] * 1e6)]
    dec = StreamingDecoder(model, taxels=[1], start_us=0)
    got = {}
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        sel = (t >= lo) & (t < hi)
        for step, values in dec.push(t[sel], np.ones(sel.sum(), int), cls[sel], {c: int(hi) for c in CLASSES}):
            got[step] = values[0]
    common = [i for i, s in enumerate(steps) if int(s) in got]
    assert len(common) > 20
    np.testing.assert_array_equal(np.stack([got[int(steps[i])] for i in common]), expected[common])
