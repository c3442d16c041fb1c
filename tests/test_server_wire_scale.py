"""/v1/stream at the size of a large skin, against a real uvicorn server: the hello fits the limits of
any client, a region subscription gets exactly the taxels of the region, and its frames decode."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest
from server_harness import collect, connect, hello_and_subscribe, running_server, until
from touchreal_client import protocol as P

from touchreal.server.settings import RuntimeConfig

#: a skin whose region's channels (every taxel's, where the region covers it) stream without shedding here; the
#: hello lists no taxel of it once P.HELLO_LISTED_TAXELS is lowered below its size
TAXELS = 1024  # 32 x 32


@pytest.mark.slow  # the region's channels of ~500 taxels: 15-40 s here (pytest -m slow; .ci/run runs it)
def test_a_large_skin_says_hello_in_a_few_hundred_bytes_and_serves_a_region(tmp_path, monkeypatch):
    monkeypatch.setattr(P, "HELLO_LISTED_TAXELS", 256)  # what a skin over 4,096 taxels gets
    with running_server(tmp_path, RuntimeConfig(taxels=TAXELS)) as (addr, svc):

        async def go():
            async with connect(addr, max_size=None) as ws:  # as touchreal_client's AsyncStream: frames have no limit
                text = await ws.recv()
                hello = json.loads(text)
                pos = P.hello_positions(hello)
                # x in [-100, 100] mm, y in [0, 50] mm, and the last 384 ids
                region = {"ranges": [[TAXELS - 384, TAXELS]], "rects": [{"x_mm": [-100, 100], "y_mm": [-10, 50]}]}
                await ws.send(json.dumps({"type": "subscribe", "classes": ["SA1"], "streams": ["spikes", "channels"],
                                          "region": region}))
                got = await collect(ws, 60.0, lambda fs: any(isinstance(f, P.ChannelsFrame) for f in fs)
                                    and sum(isinstance(f, P.SpikesFrame) for f in fs) >= 3,
                                    what="channels and spikes frames of the region")
                await until(lambda: svc.hub.demand.columns.get("SA1"), 10, "the demand follows the region")
                return text, hello, pos, got, svc.hub.demand  # while subscribed

        text, hello, pos, got, demand = asyncio.run(asyncio.wait_for(go(), 120))
    assert len(text) < 4096 and hello["n_taxels"] == TAXELS and hello["taxels"] is None  # any client's limits
    assert hello["layout"] == {"kind": "grid", "rows": 32, "cols": 32, "x0_mm": -155.0, "y0_mm": -155.0,
                               "dx_mm": 10.0, "dy_mm": 10.0}
    x, y = pos.T
    in_rect = np.flatnonzero((x >= -100) & (x <= 100) & (y >= -10) & (y <= 50))
    assert in_rect.size == 20 * 6  # x = -95, -85, ..., 95 and y = -5, 5, ..., 45 (a 10 mm grid centred on 0)
    want = sorted(set(in_rect.tolist()) | set(range(TAXELS - 384, TAXELS)))
    subscribed = next(m for m in got if isinstance(m, dict) and m["type"] == "subscribed")
    assert subscribed["region"]["ranges"] == [[TAXELS - 384, TAXELS]] and subscribed["taxels"] is None
    channels = [f for f in got if isinstance(f, P.ChannelsFrame)]
    assert all(f.taxels.tolist() == want for f in channels)  # exactly the region's taxels, in id order
    spikes = [f for f in got if isinstance(f, P.SpikesFrame)]
    assert all(set(f.taxel.tolist()) <= set(want) and set(f.cls.tolist()) <= {0} for f in spikes)
    assert demand.columns == {"SA1": tuple(want)} and demand.channel_taxels == tuple(want)


def test_a_16384_taxel_skin_says_hello_and_admits_a_region_at_once(tmp_path):
    """At 16,384 taxels: the hello the service sends, the demand a region subscription makes, and
    /v1/status, which gives it as id ranges (frames of the largest skin: tests/test_server_realtime.py)."""
    with running_server(tmp_path, RuntimeConfig(taxels=16384)) as (addr, svc):

        async def go():
            async with connect(addr, max_size=P.MAX_CLIENT_MESSAGE_BYTES) as ws:  # no more than a server accepts
                hello, subscribed = await hello_and_subscribe(ws, classes=["RA"], region={"ranges": [[100, 16384]]})
                await until(lambda: svc.hub.demand.columns.get("RA"), 10, "the demand follows the region")
                async with httpx.AsyncClient(base_url=f"http://{addr}") as http:
                    status = await http.get("/v1/status")
                return hello, subscribed, svc.hub.demand, status

        hello, subscribed, demand, status = asyncio.run(asyncio.wait_for(go(), 60))
    assert hello["n_taxels"] == 16384 and hello["taxels"] is None and P.hello_positions(hello).shape == (16384, 2)
    assert subscribed["region"] == {"ranges": [[100, 16384]], "rects": []}
    assert demand.columns == {"RA": tuple(range(100, 16384))}
    assert status.json()["demand"]["columns"] == {"RA": [[100, 16384]]}
    assert len(status.content) < 16_000, f"/v1/status is {len(status.content)} bytes"
