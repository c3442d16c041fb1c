"""Exported decoders: onnxruntime against scikit-learn, metadata, validation errors, the model store."""

from __future__ import annotations

import json
import shutil

import numpy as np
import onnx
import pytest

from touchreal.decoding.export import META_KEY, predict_labels, set_metadata, to_onnx
from touchreal.decoding.model import DecoderModelError, ModelStore, load_model, params_hash, params_warning, write_model
from touchreal.decoding.plan import ModelSpec
from touchreal.decoding.train import feature_spec, fit_pipeline, metadata
from touchreal.params import default_params


def _texture_data(rng, n_trials: int, n_bins: int):
    """PC-like counts of three 'textures': periodic at different rates plus Poisson noise."""
    xs, ys, gs = [], [], []
    for g in range(n_trials):
        lab = g % 3
        period = (2, 5, 9)[lab]
        for _ in range(20):
            phase = rng.integers(period)
            lam = 0.3 + 1.5 * (((np.arange(n_bins) + phase) % period) == 0)
            xs.append(rng.poisson(lam)[:, None])
            ys.append(f"comb_{lab}")
            gs.append(g)
    return np.asarray(xs, np.float32), np.asarray(ys, object), np.asarray(gs)


def _force_data(rng, n: int, n_bins: int):
    force = rng.uniform(0, 8, n)
    sa1 = rng.poisson(np.outer(force, np.ones(n_bins)) * 0.5)
    ra = rng.poisson(np.abs(rng.normal(0, 1, (n, n_bins))))
    return np.stack([sa1, ra], -1).astype(np.float32), force


def _export(tmp_path, spec, counts, target, groups):
    fs = feature_spec(spec)
    pipe = fit_pipeline(spec, fs.transform(counts), target, groups, seed=0)
    meta = metadata(spec, fs, pipe, default_params(), {"dataset": "synthetic", "protocol": "synthetic"})
    path = write_model(tmp_path, to_onnx(pipe, fs, meta), meta)
    return load_model(path), pipe, fs


@pytest.mark.parametrize("features", ["temporal", "rate", "both", "spectral"])
def test_texture_onnx_matches_sklearn(tmp_path, features):
    rng = np.random.default_rng(0)
    spec = ModelSpec(f"tex_{features}", "texture", ("PC",), 200.0, features)
    x, y, g = _texture_data(rng, 9, 20)
    model, pipe, fs = _export(tmp_path, spec, x, y, g)
    held, _, _ = _texture_data(np.random.default_rng(1), 6, 20)  # inputs never seen in training
    sess = model.session(threads=1)
    so = sess.get_session_options()
    assert so.intra_op_num_threads == 1 and so.inter_op_num_threads == 1
    proba, label = sess.run(["probabilities", "label"], {"counts": held})
    assert isinstance(proba, np.ndarray) and proba.dtype == np.float32 and proba.shape == (len(held), 3)  # no ZipMap
    ref_proba, ref_label = predict_labels(pipe, fs.transform(held))
    assert np.abs(proba - ref_proba).max() < 1e-4
    assert np.array_equal(label, ref_label)
    assert np.array_equal(label, np.argmax(proba, axis=1))
    assert model.meta["labels"] == ["comb_0", "comb_1", "comb_2"] == model.meta["output_names"]
    assert model.meta["features"]["order"] == fs.names()
    assert (ref_label == np.array([int(s[-1]) for s in _texture_data(np.random.default_rng(1), 6, 20)[1]])).mean() > 0.5  # chance: 1/3


@pytest.mark.parametrize("classes", [("SA1",), ("SA1", "RA")])
def test_force_onnx_matches_sklearn(tmp_path, classes):
    rng = np.random.default_rng(3)
    spec = ModelSpec("force_t", "force", classes, 128.0, "counts")
    x, y = _force_data(rng, 1500, 13)
    x = x[:, :, : len(classes)]
    model, pipe, fs = _export(tmp_path, spec, x, y, np.arange(len(y)) // 30)
    hx, hy = _force_data(np.random.default_rng(4), 300, 13)
    hx = hx[:, :, : len(classes)]
    out, _ = model.run(model.session(1), hx)
    ref = pipe.predict(fs.transform(hx))
    assert out.shape == (300, 1)
    assert np.max(np.abs(out[:, 0] - ref) / np.maximum(np.abs(ref), 1e-3)) < 1e-4
    assert np.corrcoef(ref, hy)[0, 1] > 0.9  # it learned something


@pytest.fixture()
def force_model(tmp_path):
    rng = np.random.default_rng(5)
    x, y = _force_data(rng, 300, 13)
    model, _, _ = _export(tmp_path / "m", ModelSpec("force", "force", ("SA1", "RA"), 128.0, "counts"), x, y, np.arange(300) // 30)
    return model


def test_metadata_records_params_and_warns_on_other_params(force_model):
    meta = force_model.meta
    p = default_params()
    assert meta["params"]["sha256"] == params_hash(p)
    assert params_warning(meta, p) is None
    other = p.model_copy(update={"preprocess": p.preprocess.model_copy(update={"window_ms": 64.0})})
    assert "active parameters" in params_warning(meta, other)
    # provenance alone does not change the hash
    assert params_hash(p.model_copy(update={"provenance": {"note": "x"}})) == params_hash(p)
    # a class high-pass changes it (a version 4 field; absent, the hash is that of the file before it)
    pc = p.classes["PC"].model_copy(update={"highpass_hz": 5.0})
    assert params_hash(p.model_copy(update={"classes": {**p.classes, "PC": pc}, "version": 4})) != params_hash(p.model_copy(update={"version": 4}))
    # the mains candidates change it unless they are the default (a set hashes as before the field)
    fixed = p.model_copy(update={"preprocess": p.preprocess.model_copy(update={"mains_candidates_hz": []})})
    assert params_hash(fixed) != params_hash(p)


def test_not_onnx_is_a_clear_error(tmp_path):
    bad = tmp_path / "force.onnx"
    bad.write_bytes(b"this is not a protobuf \x00\x01")
    with pytest.raises(DecoderModelError, match="not an ONNX model"):
        load_model(bad)


def test_sidecar_mismatch_and_missing_metadata(force_model, tmp_path):
    folder = force_model.path.parent
    side = folder / "force.json"
    meta = json.loads(side.read_text())
    meta["window_ms"] = 64.0
    side.write_text(json.dumps(meta))
    with pytest.raises(DecoderModelError, match="does not match the one embedded"):
        load_model(force_model.path)
    side.unlink()
    m = onnx.load(force_model.path)
    set_metadata(m, meta)  # embedded metadata that disagrees with the graph's input
    onnx.save(m, force_model.path)
    with pytest.raises(DecoderModelError, match="does not match"):
        load_model(force_model.path)
    del m.metadata_props[:]
    onnx.save(m, force_model.path)
    with pytest.raises(DecoderModelError, match=META_KEY):
        load_model(force_model.path)


def test_model_store_lists_shipped_and_user_models(force_model, tmp_path):
    store = ModelStore()
    shipped = {m["name"]: m for m in store.list()}
    assert {"force", "force_sa1", "force_ra", "texture", "texture_rate", "texture_both"} <= set(shipped)
    assert all(m["source"] == "shipped" and "error" not in m for m in shipped.values())
    assert shipped["texture"]["task"] == "texture" and shipped["force"]["classes"] == ["SA1", "RA"]
    user = tmp_path / "user"
    user.mkdir()
    shutil.copy(force_model.path, user / "force.onnx")
    (user / "broken.onnx").write_text("nope")
    store = ModelStore(user)
    listed = {m["name"]: m for m in store.list()}
    assert listed["force"]["source"] == "user"  # the user folder overrides the shipped model
    assert "not an ONNX model" in listed["broken"]["error"]
    assert store.path("force") == user / "force.onnx"
    assert store.load("texture").meta["labels"]
    with pytest.raises(DecoderModelError, match="no decoder model named 'nope'"):
        store.path("nope")
    with pytest.raises(DecoderModelError):
        store.load("broken")
