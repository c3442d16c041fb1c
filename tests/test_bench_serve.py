"""The fan-out benchmark's light subscribers (``touchreal bench serve``, part 2) against the real service."""

import asyncio

import numpy as np
import pytest
from touchreal_client import protocol as P

from touchreal.bench.serve import _light_clients
from touchreal.server.settings import RuntimeConfig

from server_harness import running_server


@pytest.mark.slow  # four light-client processes against a real server: ~19 s (pytest -m slow; .ci/run runs it)
def test_light_subscribers_see_every_frame_in_order_with_its_size(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=4)) as (addr, svc):
        spikes, spikes_joining = asyncio.run(_light_clients(addr, 3, 1.5, {}, settle_s=0.3))
        every, every_joining = asyncio.run(_light_clients(addr, 1, 1.5, {"streams": ["spikes", "channels"]}, settle_s=0.3))
        served = svc.hub.frames_rendered
    for joining, rows in zip(spikes_joining + every_joining, spikes + every):
        assert rows.shape[0] > 20 and rows.shape[1] == 8
        # the measured rows follow the joining ones: together every frame once (settle_s of them before)
        assert joining.shape[0] >= 0.3 * 100 and joining[-1, 5] + 1 == rows[0, 5]
        assert np.all(np.diff(rows[:, 5]) == 1) and rows[-1, 6] == 0  # seq: nothing missing, nothing dropped
        assert np.all(rows[:, 3] >= rows[:, 2]) and np.all(rows[:, 2] >= rows[:, 1])  # emitted, sent, received
        assert np.all(rows[:, 7] >= P.HEADER_LEN)
    # a spikes frame is its header, its count and 12-byte events; channels frames are larger
    assert np.all(spikes[0][:, 7] == P.HEADER_LEN + P.SPIKES_HEAD.size + spikes[0][:, 4] * P.EVENT_DTYPE.itemsize)
    assert every[0][:, 7].max() > spikes[0][:, 7].max()
    assert served > 0
