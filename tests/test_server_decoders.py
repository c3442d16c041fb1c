"""Decoders on the running service: REST listing and ONNX download, decoded outputs on the stream,
and a client running the downloaded model on the streamed spikes gets the service's outputs."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import onnx
import onnxruntime as ort
import pytest
from server_harness import client_decoded, collect, connect, decoded_stream, hello_and_subscribe, running_server
from touchreal_client import protocol as P


def test_decoder_endpoints_list_describe_and_serve_onnx(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        with httpx.Client(base_url=f"http://{addr}") as http:
            listed = http.get("/v1/decoders").json()
            names = [m["name"] for m in listed]
            assert {"force", "texture"} <= set(names)
            force = http.get("/v1/decoders/force").json()
            assert force["classes"] == ["SA1", "RA"] and force["output_names"] == ["force_N"]
            assert force["warning"] is None  # the shipped models were trained on the shipped parameters
            assert http.get("/v1/decoders/nope").status_code == 404
            assert http.get("/v1/decoders/nope/model.onnx").status_code == 404
            blob = http.get("/v1/decoders/force/model.onnx").content
    # no path of the serving machine, nor of the machine that trained a model, goes out
    for m in listed + [force]:
        assert "/" not in m["file"] and "/" not in m.get("training", {}).get("dataset_dir", ""), m
        assert str(tmp_path) not in json.dumps(m)
    assert b"/tmp/" not in blob
    model = onnx.load_from_string(blob)
    sess = ort.InferenceSession(blob, providers=["CPUExecutionProvider"])
    shape = [d if isinstance(d, int) else 1 for d in sess.get_inputs()[0].shape]
    (out,) = sess.run(None, {sess.get_inputs()[0].name: np.zeros(shape, np.float32)})
    assert model.graph.input and np.isfinite(out).all()


@pytest.mark.slow
def test_decoded_outputs_stream_and_equal_the_downloaded_model_on_the_streamed_spikes(tmp_path):
    def enough(names: list[str], fs: list) -> bool:  # over 100 force outputs and a texture one
        decoded = [names[f.decoder] for f in fs if isinstance(f, P.DecodedFrame)]
        return decoded.count("force") > 100 and "texture" in decoded

    blob, meta, names, frames = decoded_stream(tmp_path, ["force", "texture"], 6.0, enough,
                                               "6 s of the stream, over 100 force outputs and a texture one")
    decoded = [f for f in frames if isinstance(f, P.DecodedFrame)]
    force = [f for f in decoded if names[f.decoder] == "force"]
    texture = [f for f in decoded if names[f.decoder] == "texture"]
    assert len(force) > 100 and texture
    steps = np.concatenate([f.t_us for f in force]).astype(np.int64)
    assert np.all(np.diff(steps) == 32000) and steps[0] % 32000 == 0
    values = np.concatenate([f.values for f in force])[:, 0, 0]
    assert np.isfinite(values).all() and values.max() > 0.5  # the scene presses to several newtons
    probs = np.concatenate([f.values for f in texture])[:, 0, :]
    ok = ~np.isnan(probs).any(axis=1)
    assert np.allclose(probs[ok].sum(axis=1), 1.0, atol=1e-4)
    # the client side of the contract: its own binner + the downloaded ONNX on the spikes it received
    sess = ort.InferenceSession(blob, providers=["CPUExecutionProvider"])
    mine = client_decoded(frames, meta, int(steps[0]),
                          lambda counts: sess.run(None, {sess.get_inputs()[0].name: counts})[0].reshape(-1)[0])
    common = [i for i, t in enumerate(steps) if t in mine]
    assert len(common) > 100
    assert np.allclose([mine[steps[i]] for i in common], values[common], rtol=1e-5, atol=1e-6)
    # a decoder runs after its update's spikes went out: their frame comes first and was emitted before it ran
    spikes_of = {f.header.update: (i, f.header.emit_us) for i, f in enumerate(frames) if isinstance(f, P.SpikesFrame)}
    pos = {id(f): i for i, f in enumerate(frames)}
    pairs = [(spikes_of[f.header.update], (pos[id(f)], f.header.emit_us)) for f in force if f.header.update in spikes_of]
    assert len(pairs) > 100 and all(s[0] < d[0] and s[1] < d[1] for s, d in pairs)


def test_a_speed_reading_decoder_follows_the_scanning_speed_a_robot_puts(tmp_path):
    """PUT /v1/context gives texture_spatial its scanning speed: NaN before (no speed, no texture),
    probabilities from the next update on, NaN again once the robot says it stopped sliding."""
    from touchreal.decoding.export import to_onnx
    from touchreal.decoding.model import write_model
    from touchreal.decoding.plan import ModelSpec
    from touchreal.decoding.train import feature_spec, fit_pipeline, metadata, windows
    from touchreal.decoding.windows import encode
    from touchreal.params import default_params
    from touchreal.server.settings import RuntimeConfig
    from touchreal.simulator.simulate import simulate_dataset

    ds = simulate_dataset("texture-hard", tmp_path / "hard", trials=6, seed=8, reference=False, speeds_mm_s=(20.0, 50.0))
    trials = [encode(e, ds.load(e), default_params()) for e in ds.trials]
    spec = ModelSpec("texture_spatial", "texture", ("SA1", "RA", "PC"), 100.0, "spatial", bin_ms=1.0)
    fs = feature_spec(spec)
    w = windows(spec, trials)
    pipe = fit_pipeline(spec, fs.transform(w.counts, w.groups, w.speed), w.target, w.groups, seed=0)
    meta = metadata(spec, fs, pipe, default_params(), {"dataset": "t", "split": "train"})
    write_model(tmp_path / "state" / "models", to_onnx(pipe, fs, meta), meta)
    with running_server(tmp_path / "state", RuntimeConfig(taxels=1), token="tok") as (addr, svc):
        base, auth = f"http://{addr}", {"Authorization": "Bearer tok"}
        assert httpx.put(f"{base}/v1/context", json={"speed_mm_s": 30.0}, timeout=10).status_code == 401
        assert httpx.put(f"{base}/v1/context", json={"speed_mm_s": -1}, headers=auth, timeout=10).status_code == 422
        assert httpx.put(f"{base}/v1/context", json={"speed": 30}, headers=auth, timeout=10).status_code == 422

        def values(frames):
            return [f.values[k, 0] for f in frames if isinstance(f, P.DecodedFrame) for k in range(f.values.shape[0])]

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["decoded"], decoders=["texture_spatial"])
                before = await collect(ws, 30, lambda f: len(values(f)) >= 5, what="5 decoded steps")
                r = await asyncio.to_thread(httpx.put, f"{base}/v1/context", json={"speed_mm_s": 30.0}, headers=auth, timeout=10)
                assert r.status_code == 200 and r.json() == {"speed_mm_s": 30.0}
                during = await collect(ws, 30, lambda f: sum(np.isfinite(v).all() for v in values(f)) >= 5,
                                       what="5 decoded steps with the speed")
                await asyncio.to_thread(httpx.put, f"{base}/v1/context", json={"speed_mm_s": None}, headers=auth, timeout=10)
                after = await collect(ws, 30, lambda f: sum(np.isnan(v).all() for v in values(f)) >= 3,
                                      what="3 NaN steps once the speed is withdrawn")
                return values(before), values(during), values(after)

        before, during, after = asyncio.run(asyncio.wait_for(go(), 90))
        assert httpx.get(f"{base}/v1/context", timeout=10).json() == {"speed_mm_s": None}
    assert all(np.isnan(v).all() for v in before)
    finite = [v for v in during if np.isfinite(v).all()]
    assert len(finite) >= 5 and all(abs(float(v.sum()) - 1.0) < 1e-3 for v in finite)  # one probability per comb
    assert np.isnan(after[-1]).all()
