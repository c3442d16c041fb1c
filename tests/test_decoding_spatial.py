"""The scanning texture decoder: phase locking on a spatial-frequency axis, the scanning speed as a
second ONNX input.

Its features find a surface period whatever the scanning speed, the exported graph equals the
numpy features and the scikit-learn pipeline, the scanning windows follow the recorded motion, and
the streaming decoder with a speed gives the offline windows' outputs (NaN without a speed)."""

from __future__ import annotations

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from touchreal_client.features import CLASSES, StreamBinner

from touchreal.decoding.export import predict_labels, set_metadata, to_onnx
from touchreal.decoding.features import FeatureSpec
from touchreal.decoding.model import DecoderModelError, load_model, write_model
from touchreal.decoding.plan import ModelSpec, spec_from_meta
from touchreal.decoding.streaming import StreamingDecoder
from touchreal.decoding.train import feature_spec, fit_pipeline, metadata, windows
from touchreal.decoding.windows import SCAN_STEADY, encode, scan_track
from touchreal.params import default_params
from touchreal.simulator.simulate import simulate_dataset


def test_locking_peaks_at_the_surface_period_at_any_speed_and_the_graph_agrees():
    fs = FeatureSpec("spatial", 200, 3, 1.0, 200.0)
    k = fs.spatial_grid()[0]
    x = np.zeros((3, 200, 3), np.float32)
    speeds = np.array([[20.0], [40.0], [50.0]], np.float32)
    for row, v in enumerate(speeds[:, 0]):  # a 2 mm period: one RA spike per tooth, v / 2 teeth per s
        x[row, np.round(np.arange(0, 200, 2000.0 / v)).astype(int), 1] = 1
    f = fs.transform(x, speed=speeds)
    nk = k.size
    ra = f[:, 3 + nk: 3 + 2 * nk]
    low = k < 0.8  # below the second harmonic
    assert np.all(np.abs(k[low][np.argmax(ra[:, low], axis=1)] - 0.5) < 0.05)  # 1 / 2 mm, at every speed
    np.testing.assert_allclose(f[:, 1], 0.5, rtol=0.15)  # spikes per mm: one per 2 mm tooth
    assert np.all(f[:, 3: 3 + nk] == 0)  # a silent class: zero, no division by zero
    sess = ort.InferenceSession(fs.graph(17, 8).SerializeToString(), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(sess.run(None, {"counts": x, "speed_mm_s": speeds})[0], f, rtol=1e-4, atol=1e-4)
    one = sess.run(None, {"counts": x, "speed_mm_s": speeds[:1]})[0]  # one speed for every row broadcasts
    np.testing.assert_allclose(one, fs.transform(x, speed=speeds[:1]), rtol=1e-4, atol=1e-4)
    # intervals in mm: one RA spike per 2 mm tooth puts the interval histogram's mass at 2, 4, 6 ... mm at every speed
    mm = np.exp(fs.interval_grid()[0])
    ni = mm.size
    hist = f[:, 3 + 3 * nk:].reshape(3, 3, ni)
    np.testing.assert_allclose(hist[:, 1].sum(axis=1), 1.0, rtol=1e-5)  # each interval adds 1 (normalised)
    near = np.abs(np.log(mm)[None, :] - np.log([[2.0], [4.0], [6.0], [8.0]])).min(axis=0) < 0.1
    np.testing.assert_allclose(hist[:, 1, near].sum(axis=1), 1.0, rtol=1e-5)
    # 2, 4, 5 spikes: intervals to the next 1-4 spikes, 1, 3 + 2 + 1 and 4 + 3 + 2 + 1 of them, of which 1, 3, 4 at 2 mm
    np.testing.assert_allclose(hist[:, 1, np.abs(np.log(mm / 2.0)) < 0.1].sum(axis=1), [1.0, 0.5, 0.4], rtol=1e-4)
    assert np.all(hist[:, [0, 2]] == 0)  # silent classes: no interval
    # two spikes per tooth (1 ms apart) instead of one: the peak stays at the period
    two = x.copy()
    two[:, 1:, 1] = np.maximum(two[:, 1:, 1], x[:, :-1, 1])
    h2 = fs.transform(two, speed=speeds)[:, 3 + 3 * nk:].reshape(3, 3, ni)[:, 1]
    assert np.all(np.abs(mm[np.argmax(np.where(mm > 1.0, h2, 0), axis=1)] - 2.0) < 0.1)
    assert len(fs.names()) == f.shape[1] == 3 + 3 * nk + 3 * ni
    with pytest.raises(ValueError, match="speed"):
        fs.transform(x)


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
    ds = simulate_dataset("texture-hard", tmp_path_factory.mktemp("hard"), trials=8, seed=8, reference=False,
                          speeds_mm_s=(20.0, 50.0))
    p = default_params()
    return [encode(e, ds.load(e), p) for e in ds.trials]


def test_scanning_windows_follow_the_commanded_slide(hard):
    spec = ModelSpec("texture_spatial", "texture", ("SA1", "RA", "PC"), 100.0, "spatial", bin_ms=1.0)
    w = windows(spec, hard)
    for i, tr in enumerate(hard):
        ev, v = tr.entry["events"], tr.entry["params"]["speed_mm_s"]
        steps = w.steps[w.groups == i]
        assert steps.size >= 55  # 2 s of slide, 32 ms steps, 100 ms window
        slack = SCAN_STEADY * 100_000 / 4  # a quarter may fall short of the mean by SCAN_STEADY
        assert steps.min() - 100_000 >= ev["slide_start_s"] * 1e6 - slack and steps.max() <= ev["slide_end_s"] * 1e6 + slack
        np.testing.assert_allclose(w.speed[w.groups == i], v, rtol=SCAN_STEADY)
    # without cmd_x, the manifest's speed and slide events give the same windows
    bare = [type(tr)(tr.entry, tr.spikes_us, tr.st_t_us, tr.st, tr.end_us) for tr in hard[:2]]
    assert windows(spec, bare).steps.size == 0  # no scan information at all: no scanning window
    class NoX:
        cmd_x = None

    same = [type(tr)(tr.entry, tr.spikes_us, tr.st_t_us, tr.st, tr.end_us, *scan_track(tr.entry, NoX())) for tr in hard[:2]]
    np.testing.assert_array_equal(windows(spec, same).steps, w.steps[w.groups < 2])


@pytest.fixture(scope="module")
def spatial_model(hard, tmp_path_factory):
    spec = ModelSpec("texture_spatial", "texture", ("SA1", "RA", "PC"), 100.0, "spatial", bin_ms=1.0)
    fs = feature_spec(spec)
    w = windows(spec, hard[:6])
    pipe = fit_pipeline(spec, fs.transform(w.counts, w.groups, w.speed), w.target, w.groups, seed=0)
    meta = metadata(spec, fs, pipe, default_params(), {"dataset": "t", "split": "train"})
    path = write_model(tmp_path_factory.mktemp("m"), to_onnx(pipe, fs, meta), meta)
    return load_model(path), pipe, fs, spec


def test_exported_spatial_model_equals_scikit_learn_through_onnxruntime(spatial_model, hard):
    model, pipe, fs, spec = spatial_model
    assert model.needs_speed and model.meta["alignment"] is None and spec_from_meta(model.meta) == spec
    w = windows(spec, hard[6:])  # trials never trained on
    out = model.run_windows(model.session(1), w.counts, w.groups, w.speed, chunk=50)
    proba, label = predict_labels(pipe, fs.transform(w.counts, speed=w.speed))
    np.testing.assert_allclose(out, proba, atol=1e-4)
    sess = ort.InferenceSession(model.onnx_bytes, providers=["CPUExecutionProvider"])
    p, lab = sess.run(["probabilities", "label"], {"counts": w.counts, "speed_mm_s": w.speed})
    np.testing.assert_array_equal(lab, label)
    with pytest.raises(ValueError, match="speed"):
        model.run(model.session(1), w.counts[:1])


def test_streaming_with_the_speed_equals_the_offline_windows(spatial_model, hard):
    model, _, _, spec = spatial_model
    tr = hard[7]
    w = windows(spec, [tr])
    expected = model.run_windows(model.session(1), w.counts, w.groups, w.speed)
    t = np.concatenate([tr.spikes_us[c] for c in CLASSES])
    cls = np.concatenate([np.full(tr.spikes_us[c].size, i) for i, c in enumerate(CLASSES)])
    o = np.argsort(t, kind="stable")
    t, cls = t[o].astype(np.uint64), cls[o]
    # the robot reports its speed while it slides: the speed of each step's window, as the offline windows measure it
    # (the interval histograms move with it: a nominal 20 mm/s against a measured 20.00002 differs by a few 1e-6)
    v = dict(zip(w.steps.tolist(), w.speed[:, 0].tolist()))
    scanning = set(w.steps.tolist())
    dec = StreamingDecoder(model, [3], start_us=0)
    got = {}
    for lo in range(0, tr.end_us, 8000):  # 8 ms updates, each completing at most one 32 ms step
        sel = (t >= lo) & (t < lo + 8000)
        speed = v.get(-(-(lo + 8000) // 32000) * 32000)
        for step, values in dec.push(t[sel], np.full(sel.sum(), 3), cls[sel], {c: lo + 8000 for c in CLASSES}, speed):
            got[step] = values[0]
    np.testing.assert_allclose(np.array([got[s] for s in w.steps]), expected, rtol=1e-5, atol=1e-6)
    idle = [s for s in got if s not in scanning]
    assert idle and all(np.isnan(got[s]).all() for s in idle)  # no speed: no texture
    # a client's own binner + the file through onnxruntime, one speed row for the batch
    binner = StreamBinner.from_metadata(model.meta, [3], start_us=0)
    sess = ort.InferenceSession(model.onnx_bytes, providers=["CPUExecutionProvider"])
    mine = {}
    for step, counts, _ in binner.push(t, np.full(t.size, 3), cls, {c: tr.end_us for c in CLASSES}):
        if step in scanning:
            mine[step] = sess.run(["probabilities"], {"counts": counts, "speed_mm_s": np.full((1, 1), v[step], np.float32)})[0][0]
    np.testing.assert_allclose(np.array([mine[s] for s in w.steps]), expected, rtol=1e-5, atol=1e-6)


def test_context_metadata_is_validated(spatial_model, tmp_path):
    model, _, _, _ = spatial_model
    bad = json.loads(json.dumps(model.meta))
    bad["context"]["unit"] = "m/s"
    m = onnx.load_from_string(model.onnx_bytes)
    set_metadata(m, bad)
    with pytest.raises(DecoderModelError, match="context"):
        load_model(write_model(tmp_path, m, bad))
    gone = json.loads(json.dumps(model.meta))
    gone["context"] = None  # the graph still has the speed input
    set_metadata(m, gone)
    with pytest.raises(DecoderModelError, match="graph inputs"):
        load_model(write_model(tmp_path / "b", m, gone))
