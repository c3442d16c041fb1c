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
    with_st = [c for c in chunks if c.st_t.size]
    assert len(with_st) >= 20 and all(c.st_t.size == 1 and c.st_t[-1] == c.pvdf_t[-1] for c in with_st)
    assert all(c.pvdf_t.size == 10 for c in chunks[1:])  # 5 ms hops after the aligning first chunk
    # paced: a chunk is released at the instant of its newest sample (the first one at the first call)
    assert time.monotonic() - t0 >= pv[-1] - chunks[0].pvdf_t[-1]
    clock = src.clock()
    assert clock.sensor_us == round(pv[-1] * 1e6) and clock.rate == 1.0
    src.close()
    assert src.next_chunk() is None
