"""The live simulated e-skin's hop: a chunk ends with each SingleTact sample and halfway between."""

import time

import numpy as np
import pytest

from touchreal.sensing.live import SimLiveSource


@pytest.mark.parametrize("seed", [0, 3])
def test_sim_hop_ends_a_chunk_with_each_singletact_sample(seed):
    src = SimLiveSource(2, 0.005, seed=seed)
    t0 = time.monotonic()
    chunks = [src.next_chunk() for _ in range(41)]
    pv = np.concatenate([c.pvdf_t for c in chunks])
    assert np.allclose(np.diff(pv), 0.0005)  # every tick once, in order
    st = np.concatenate([c.st_t for c in chunks])
    assert st.size >= 20 and np.allclose(np.diff(st), 0.01)
    # every chunk ends with a SingleTact sample (and its PVDF tick) or halfway between two
    half = (np.array([c.pvdf_t[-1] for c in chunks]) - st[0]) / 0.005
    assert np.allclose(half, np.round(half))
    assert all(c.st_t[-1] == c.pvdf_t[-1] for c, h in zip(chunks, np.round(half)) if h % 2 == 0)
    assert all(c.pvdf_t.size % 10 == 0 for c in chunks[1:])  # whole 5 ms hops after the aligning first chunk
    # paced: a chunk is released at the instant of its newest sample (the first one at the first call)
    assert time.monotonic() - t0 >= pv[-1] - chunks[0].pvdf_t[-1]
    clock = src.clock()
    assert clock.sensor_us == round(pv[-1] * 1e6) and clock.rate == 1.0
    src.close()
    assert src.next_chunk() is None


def test_a_consumer_that_fell_behind_gets_the_due_hops_in_one_chunk():
    src = SimLiveSource(1, 0.005, seed=1)
    first = src.next_chunk()
    time.sleep(0.1)  # ~20 hops come due meanwhile
    late = src.next_chunk()
    assert 15 <= late.pvdf_t.size // 10 <= 64  # the due hops at once, not one per call
    assert np.allclose(np.diff(np.concatenate([first.pvdf_t, late.pvdf_t])), 0.0005)
    assert src.clock().sensor_us == round(late.pvdf_t[-1] * 1e6)
    assert src.next_chunk().pvdf_t.size < late.pvdf_t.size  # catching up
    src.close()
