"""StreamingDecoder: pushed spike events give exactly the offline windows' outputs."""

from __future__ import annotations

import numpy as np
import pytest
from touchreal_client.features import CLASSES

from touchreal.decoding.model import ModelStore
from touchreal.decoding.plan import spec_from_meta
from touchreal.decoding.streaming import StreamingDecoder
from touchreal.decoding.train import windows
from touchreal.decoding.windows import encode
from touchreal.params import default_params
from touchreal.simulator.simulate import simulate_dataset


@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    ds = simulate_dataset(["ramp", "texture"], tmp_path_factory.mktemp("sim"), trials={"ramp": 1, "texture": 1}, seed=5, reference=False)
    p = default_params()
    return {e["protocol"]: encode(e, ds.load(e), p) for e in ds.trials}


def _events(tr, taxel: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.concatenate([tr.spikes_us[c] for c in CLASSES])
    cls = np.concatenate([np.full(tr.spikes_us[c].size, i) for i, c in enumerate(CLASSES)])
    o = np.argsort(t, kind="stable")
    return t[o].astype(np.uint64), np.full(t.size, taxel), cls[o]


def _stream(dec, events, bounds_us) -> dict[int, np.ndarray]:
    t, tax, cls = events
    got: dict[int, np.ndarray] = {}
    for lo, hi in zip(bounds_us[:-1], bounds_us[1:]):
        sel = (t >= lo) & (t < hi)
        for step, values in dec.push(t[sel], tax[sel], cls[sel], {c: int(hi) for c in CLASSES}):
            assert step not in got and values.dtype == np.float32
            got[step] = values
    return got


@pytest.mark.parametrize("name,protocol", [("force", "ramp"), ("texture", "texture")])
def test_stream_equals_offline_windows(trials, name, protocol):
    model = ModelStore().load(name)
    tr = trials[protocol]
    counts, _, _, steps, _ = windows(spec_from_meta(model.meta), [tr])
    assert steps.size > 10
    expected, _ = model.run(model.session(1), counts)
    t, _, cls = _events(tr, 3)
    noise = np.sort(np.random.default_rng(0).integers(0, tr.end_us, 300)).astype(np.uint64)
    events = (np.concatenate([t, noise]), np.concatenate([np.full(t.size, 3), np.full(noise.size, 4)]),
              np.concatenate([cls, np.full(noise.size, 2)]))  # taxel 4 is not decoded: ignored
    rng = np.random.default_rng(1)
    bounds = np.concatenate(([0], np.cumsum(rng.integers(1_000, 70_000, 200))))  # irregular updates
    bounds = bounds[bounds < tr.end_us + 100_000]
    dec = StreamingDecoder(model, taxels=[9, 3], threads=1, start_us=0)
    got = _stream(dec, events, bounds)
    assert sorted(got) == list(range(0, int(bounds[-1]) + 1, 32_000))  # every step once, in order, none late
    out = np.stack([got[int(s)][1] for s in steps])
    np.testing.assert_array_equal(out, expected)
    silent = np.stack([got[int(s)][0] for s in steps])
    if name == "texture":
        assert np.isnan(silent).all()  # no PC spike on taxel 9: no anchor, no output
        assert len(dec.output_names) == 3 and np.allclose(out.sum(axis=1), 1.0, atol=1e-5)
    else:
        assert dec.output_names == ["force_N"] and np.isfinite(silent).all()


def test_stream_waits_for_every_class_and_validates_input(trials):
    model = ModelStore().load("force")
    dec = StreamingDecoder(model, taxels=[0], start_us=0)
    empty = np.zeros(0, np.uint64)
    assert [s for s, _ in dec.push(empty, empty, empty, {"SA1": 100_000, "RA": 40_000, "PC": 0})] == [0, 32_000]
    assert [s for s, _ in dec.push(empty, empty, empty, {"SA1": 100_000, "RA": 100_000, "PC": 0})] == [64_000, 96_000]
    with pytest.raises(ValueError, match="final_us lacks"):
        dec.push(empty, empty, empty, {"SA1": 200_000})
    with pytest.raises(ValueError, match="cls indexes"):
        dec.push(np.array([1], np.uint64), np.array([0]), np.array([5]), {"SA1": 0, "RA": 0})
    with pytest.raises(ValueError, match="distinct"):
        StreamingDecoder(model, taxels=[1, 1])
    late = StreamingDecoder(model, taxels=[0])  # no start: the first step is at the first completeness time
    assert late.push(empty, empty, empty, {"SA1": 50_000, "RA": 70_000}) == []  # first step: 64 ms
    assert [s for s, _ in late.push(empty, empty, empty, {"SA1": 70_000, "RA": 70_000})] == [64_000]


def test_client_side_binner_with_its_own_session_matches_the_service(trials):
    """A client: the downloaded ONNX bytes, metadata read back by onnxruntime, StreamBinner."""
    import json

    import onnxruntime as ort
    from touchreal_client.features import META_KEY, StreamBinner

    model = ModelStore().load("texture")
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = 1, 1
    sess = ort.InferenceSession(model.onnx_bytes, so, providers=["CPUExecutionProvider"])
    meta = json.loads(sess.get_modelmeta().custom_metadata_map[META_KEY])
    assert meta == model.meta
    binner = StreamBinner.from_metadata(meta, [3], start_us=0)
    dec = StreamingDecoder(model, [3], start_us=0)
    t, tax, cls = _events(trials["texture"], 3)
    for lo in range(0, trials["texture"].end_us, 32_000):
        sel = (t >= lo) & (t < lo + 32_000)
        final = {c: lo + 32_000 for c in CLASSES}
        ours = dec.push(t[sel], tax[sel], cls[sel], final)
        theirs = binner.push(t[sel], tax[sel], cls[sel], final)
        assert [s for s, _ in ours] == [s for s, _, _ in theirs]
        for (_, v), (_, counts, filled) in zip(ours, theirs):
            if filled[0]:
                (p, label) = sess.run(["probabilities", "label"], {"counts": counts})
                np.testing.assert_array_equal(v, p)
                assert label[0] == np.argmax(v[0])


def test_binner_reanchors_after_silence_like_the_offline_rule():
    from touchreal_client import features as F

    rng = np.random.default_rng(7)
    burst1 = np.sort(rng.integers(100_000, 900_000, 60))
    burst2 = np.sort(rng.integers(1_600_000, 2_500_000, 60))  # > 500 ms after burst 1: a new anchor
    pc = np.concatenate([burst1, burst2])
    align = {"rule": F.ALIGN_RULE, "class": "PC", "silence_ms": 500.0}
    binner = F.StreamBinner(["PC"], [0], 300_000, alignment=align, start_us=0)
    got = {}
    for lo in range(0, 2_700_000, 45_000):
        sel = (pc >= lo) & (pc < lo + 45_000)
        for step, counts, filled in binner.push(pc[sel], np.zeros(sel.sum(), int), np.full(sel.sum(), 2), {"PC": lo + 45_000}):
            got[step] = (counts[0, :, 0], filled[0])
    steps = np.array(sorted(got))
    ends, anchor = F.anchored_end(steps, F.anchors(pc, 500_000))
    ok = F.ready(ends, anchor, 300_000)
    assert set(anchor[ok]) == {burst1[0], burst2[0]}
    expected = F.window_counts(pc, ends[ok], 300_000)
    np.testing.assert_array_equal(np.stack([got[s][0] for s in steps[ok]]), expected)
    assert [got[s][1] for s in steps] == ok.tolist()
