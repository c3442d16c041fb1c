"""The float32 compute path (``StreamEncoder(dtype=np.float32)``): float32 through the chain, and its
spikes within the documented bound of float64's on the same input (docs/benchmarks.md, Encoder)."""

import numpy as np
import pytest

from touchreal.analysis.spiketrains import vr_distance
from touchreal.encoding.encoder import SpikeEvents
from touchreal.params import default_params
from touchreal.preprocess.resample import pchip_eval
from touchreal.preprocess.stft_gate import StftGate
from touchreal.raw import taxel_grid
from touchreal.simulator.scene import SceneSource
from touchreal.settings import CLASSES
from touchreal.stream import StreamEncoder

#: state that stays float64 by design: raw acquisition (sanitizers, history rings), the 100 Hz
#: alpha-beta tracker, the PVDF low-pass + notch cascade (float32 notches err by ~1e-3 of the range)
#: and the encoder's class low-pass, lead and membrane (float64 accumulators)
FLOAT64_STATE = {"st_last", "pv_last", "st_hist", "pv_hist", "st_ab_v", "st_ab_x", "pv_filter", "lif_v", "input_lowpass", "input_highpass", "input_lead"}

CHANNEL_BOUND = 1e-5  #: |float32 - float64| channel, fraction of the channel's range (documented bound)
COUNT_BOUND = 0.01  #: |float32 - float64| spike count, fraction of float64's per class (documented bound)
VR_BOUND = 0.05  #: mean van Rossum distance (tau 10 ms) per taxel and class (documented bound)


def _scene(n_taxels: int, seconds: float, seed: int = 1) -> list:
    """A contact scene on a dense grid (3 mm pitch): every class spikes on most taxels."""
    src = SceneSource(taxels_xy_mm=taxel_grid(n_taxels, pitch_mm=3.0), seed=seed)
    return [src.read(0.032) for _ in range(int(round(seconds / 0.032)))]


def _encode(chunks: list, n_taxels: int, dtype: type) -> tuple[StreamEncoder, np.ndarray, SpikeEvents]:
    se = StreamEncoder(default_params(), n_taxels, dtype=dtype)
    chans, events = [], []
    for c in chunks:
        ch, ev = se.process_channels(c)
        chans.append(ch.data)
        events.append(ev)
    return se, np.concatenate(chans), SpikeEvents.concatenate(events + [se.finish()])


def _stripped(name: str) -> str:
    """A state array's name without its source prefix (``st_`` / ``128ms_`` of encoder states)."""
    for prefix in ("st_lif", "st_input"):
        if name.startswith(prefix):
            return name[3:]
    head, _, rest = name.partition("ms_")
    return rest if rest and head.replace(".", "").isdigit() else name


@pytest.fixture(scope="module")
def both() -> dict:
    chunks = _scene(16, 6.0)
    return {dt: _encode(chunks, 16, dt) for dt in (np.float64, np.float32)}


def test_pchip_and_gate_compute_in_float32():
    """Each stage returns float32 for float32 input, close to float64 but not float64's result
    rounded (which a stage that widens internally and narrows at the end would return)."""
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.uniform(0.009, 0.011, 12)) + 100.0  # knot times (s), far from 0 like a live clock
    y = rng.normal(size=(12, 64)).astype(np.float32)
    t = np.linspace(x[1], x[-2], 200, endpoint=False)
    got, ref = pchip_eval(x, y, t), pchip_eval(x, y.astype(np.float64), t)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    assert not np.array_equal(got, ref.astype(np.float32))

    sig = rng.normal(size=(400, 32)).astype(np.float32)
    thr = np.full(33, 2.0)
    g32, g64 = StftGate(64, 32, thr, dtype=np.float32), StftGate(64, 32, thr, dtype=np.float64)
    got, ref = g32.process(sig), g64.process(sig.astype(np.float64))
    assert got.dtype == np.float32 and g32._acc.dtype == np.float32 and g32._buf.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    assert not np.array_equal(got, ref.astype(np.float32))


def test_float32_chain_keeps_float32(both):
    """Channels and every preprocessing state array are float32; only the documented float64 state is not."""
    se, chans, _ = both[np.float32]
    assert chans.dtype == np.float32
    wide = {_stripped(k) for k, a in se.state_arrays().items() if a.dtype != np.float32}
    assert wide <= FLOAT64_STATE, f"stages widened to float64: {sorted(wide - FLOAT64_STATE)}"
    assert {"pv_filter", "pv_filtered", "st_lp", "st_rs"} <= {_stripped(k) for k in se.state_arrays()}
    assert any(k.endswith("_gate_acc") for k in se.state_arrays())
    _, chans64, _ = both[np.float64]
    assert chans64.dtype == np.float64


def test_float32_spikes_within_bound_of_float64(both):
    _, c64, ev64 = both[np.float64]
    _, c32, ev32 = both[np.float32]
    m = min(len(c64), len(c32))
    scale = np.nanmax(np.abs(c64[:m]), axis=(0, 1))
    assert np.all(np.nanmax(np.abs(c32[:m] - c64[:m]), axis=(0, 1)) <= CHANNEL_BOUND * scale)  # per channel, relative to its range
    for c in CLASSES:
        n64 = np.array([len(ev64.train(c, x)) for x in range(16)])
        n32 = np.array([len(ev32.train(c, x)) for x in range(16)])
        assert n64.sum() > 50, f"the scene must make {c} spike"
        assert np.abs(n32 - n64).sum() <= COUNT_BOUND * n64.sum() + 1, c
        vr = np.mean([vr_distance(ev32.train(c, x), ev64.train(c, x), 0.01) for x in range(16)])
        assert vr <= VR_BOUND, c
