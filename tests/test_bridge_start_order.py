"""Whatever the start order of service (with its publisher), gateway and client, through a real
nats-server: the client ends up with the service's hello and its frames."""

from __future__ import annotations

import asyncio
import json
from contextlib import AsyncExitStack

import pytest
from server_harness import collect, connect, n_spikes
from test_bridge_nats import SENSOR, publishing
from touchreal_client import protocol as P

from touchreal.bridge.gateway import Gateway, create_gateway_app
from touchreal.bridge.settings import GatewaySettings
from touchreal.server.app import serving_app

FRAMES = 10  #: spike frames the client must receive


async def _start_in_order(order: tuple[str, ...], state_dir, url: str, stack: AsyncExitStack) -> tuple[list, list, object]:
    """Start each of "service", "gateway", "client" in ``order`` (nothing waits for anything upstream);
    then read until the client holds a hello with taxels and FRAMES spike frames (30 s bound a failure).
    Returns (the client's hellos, its spike frames, the service)."""
    gw = Gateway(GatewaySettings(nats=url, sensor_id=SENSOR, host="127.0.0.1", port=0))
    svc, ws, ga = None, None, None
    for step in order:
        if step == "service":
            _addr, svc, _pub = await asyncio.to_thread(stack.enter_context, publishing(state_dir, url))
        elif step == "gateway":
            ga = await asyncio.to_thread(stack.enter_context, serving_app(create_gateway_app(gw)))
        else:
            # it reads no more once it holds its frames: an unbounded queue lets its close handshake through
            # at once (a full one stops websockets reading the socket, so the close waited 10 s for its timeout)
            ws = await stack.enter_async_context(connect(ga, max_queue=None))
            await ws.send(json.dumps({"type": "subscribe"}))

    def hellos_in(got: list) -> list[dict]:
        return [m for m in got if isinstance(m, dict) and m["type"] == "hello"]

    got = await collect(ws, 30.0, lambda fs: (h := hellos_in(fs)) and h[-1]["taxels"] and n_spikes(fs) >= FRAMES,
                        what=f"a hello with taxels and {FRAMES} spikes frames")
    return hellos_in(got), [f for f in got if isinstance(f, P.SpikesFrame)], svc


def _check(hellos: list, frames: list, svc) -> None:
    assert hellos and hellos[-1]["session"] == svc.session and len(hellos[-1]["taxels"]) == 1, hellos[-1:]
    assert len(frames) >= FRAMES and all(f.final_us["SA1"] is not None for f in frames)
    seqs = [f.header.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


@pytest.mark.parametrize("order", [("service", "gateway", "client"), ("gateway", "service", "client")])
def test_client_gets_frames_whatever_the_start_order(tmp_path, nats_url, order):  # noqa: F811
    async def go():
        async with AsyncExitStack() as stack:
            return await _start_in_order(order, tmp_path, nats_url, stack)

    _check(*asyncio.run(asyncio.wait_for(go(), 90)))


def test_gateway_and_client_before_the_service(tmp_path, nats_url):  # noqa: F811
    """The client subscribes against the gateway's placeholder hello (no taxels); it gets the real
    hello and its frames as soon as the service appears. Repeated: the order was racy."""
    from touchreal.bridge import natsd

    for run in range(3):
        # a broker of its own per run: nothing of the previous run's publisher can answer on it
        with natsd.local_nats_server() as url:
            async def go():
                async with AsyncExitStack() as stack:
                    return await _start_in_order(("gateway", "client", "service"), tmp_path / str(run), url, stack)

            hellos, frames, svc = asyncio.run(asyncio.wait_for(go(), 90))
        assert hellos[0]["taxels"] == [] and hellos[0]["session"] is None  # the placeholder came first
        _check(hellos, frames, svc)
