"""touchreal_client against a real service on 127.0.0.1: the stream (sync and async), subscription
changes, clock sync and latency, JSON encoding, reconnect after a server restart, fatal closes."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import pytest
from server_harness import free_port, running_server
from touchreal_client import (AsyncClient, Backoff, Client, ServiceUnavailable, SpikesFrame, StreamClosed, StreamError,
                              Subscription)
from touchreal_client import protocol as P

from touchreal.server.settings import RuntimeConfig


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


def take(it, n: int, seconds: float = 20.0) -> list:
    out, end = [], time.monotonic() + seconds
    for f in it:
        out.append(f)
        if len(out) >= n or time.monotonic() > end:
            break
    return out


def test_sync_client_streams_spikes_as_numpy_arrays_with_stats_and_latency(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=2)) as (addr, svc):
        with Client(f"http://{addr}") as tr:
            tr.wait_ready(30)
            with tr.stream() as s:
                assert s.hello["session"] == svc.session and [t["id"] for t in s.hello["taxels"]] == [0, 1]
                offset = s.sync_clock(5)
                frames = take(s.spikes(), 300)  # ~1.5 s of 5 ms hops
                stats, summary = s.stats, s.latency.summary()
    assert len(frames) == 300 and all(isinstance(f, SpikesFrame) for f in frames)
    t = np.concatenate([f.t_us for f in frames])
    assert t.dtype == np.uint64 and t.size > 0  # the simulated scene touches within ~1 s
    assert set(np.concatenate([f.taxel for f in frames]).tolist()) <= {0, 1}
    assert stats.frames >= 300 and stats.gaps == 0 and stats.missed_frames == 0 and stats.connections == 1
    assert stats.spike_events >= t.size
    assert abs(offset) < 50_000  # one machine: the clocks agree within the exchange's round trip
    assert summary.offset_uncertainty_us is not None and summary.offset_uncertainty_us < 50_000
    assert 0 <= summary.delivery_median_us < 1_000_000
    assert summary.total_median_us["SA1"] >= s.hello["latency_us"]["SA1"]


def test_async_subscription_changes_json_encoding_and_refused_subscriptions(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=4)) as (addr, svc):

        async def go():
            async with AsyncClient(f"http://{addr}") as tr:
                await tr.wait_ready(30)
                async with tr.stream(Subscription(taxels=[1], classes=["SA1"], encoding="json")) as s:
                    first = [f async for f in _first(s.spikes(), 15)]
                    reply = await s.subscribe(taxels=[2, 3], classes=["PC"], encoding="binary")
                    with pytest.raises(StreamError, match="SA9"):
                        await s.subscribe(classes=["SA9"])
                    second = [f async for f in _first(s.spikes(), 40)]
                    return first, reply, second, s.subscription, dict(svc.hub.demand.columns)

        first, reply, second, kept, demand = run(go())
    assert all(f.final_us["RA"] is None and set(f.taxel.tolist()) <= {1} and set(f.cls.tolist()) <= {0} for f in first)
    assert reply["type"] == "subscribed" and reply["taxels"] == [2, 3] and reply["classes"] == ["PC"]
    assert kept.classes == ["PC"]  # the refused subscription did not replace the accepted one
    late = [f for f in second if f.final_us["PC"] is not None]
    assert late and all(set(f.taxel.tolist()) <= {2, 3} and set(f.cls.tolist()) <= {2} for f in late)
    assert demand == {"PC": (2, 3)}


async def _first(agen, n):
    i = 0
    async for f in agen:
        yield f
        i += 1
        if i >= n:
            return


def test_reconnects_with_backoff_after_a_server_restart_and_resubscribes(tmp_path):
    port = free_port()
    sub = Subscription(classes=["SA1", "RA"], streams=["spikes", "channels"], decimation=100)
    with Client(f"http://127.0.0.1:{port}") as tr:
        with running_server(tmp_path, port=port) as (_, svc1):
            tr.wait_ready(30)
            s = tr.stream(sub, backoff=Backoff(initial_s=0.05, max_s=0.5, seed=0))
            s.open()
            it = s.frames()
            before = take(it, 10)
            session1 = s.hello["session"]
        with running_server(tmp_path, port=port) as (_, svc2):  # the old one closed us with 1001
            after = take(it, 200, seconds=40)  # past the 128 ms window's start (channels), in 5 ms hops
            stats, hello, subscribed = s.stats, s.hello, s.subscribed
        s.close()
    assert len(before) == 10 and len(after) == 200
    assert session1 == svc1.session and hello["session"] == svc2.session != session1
    assert stats.connections == 2 and stats.session_changes == 1 and stats.gaps == 0
    assert subscribed["classes"] == ["SA1", "RA"] and subscribed["channels"] == {"decimation": 100}
    assert any(isinstance(f, P.ChannelsFrame) for f in after)
    assert all(f.final_us["PC"] is None for f in after if isinstance(f, SpikesFrame))


def test_fatal_close_ends_iteration_and_unreachable_service_is_a_clear_error(tmp_path):
    with running_server(tmp_path) as (addr, _):

        async def go():
            async with AsyncClient(f"http://{addr}").stream(Subscription()) as s:
                await s._ws.send("x" * (P.MAX_CLIENT_MESSAGE_BYTES + 1))  # the server closes with 1009
                with pytest.raises(StreamClosed) as closed:
                    async for _ in s.frames():
                        pass
                return closed.value

        closed = run(go())
    assert closed.code == P.CLOSE_TOO_BIG
    with pytest.raises(ServiceUnavailable, match="cannot open"):
        run(AsyncClient(f"http://127.0.0.1:{free_port()}").stream().open())


def test_a_malformed_frame_from_a_peer_ends_iteration_with_the_protocol_error():
    """A loopback WebSocket peer that says hello and then sends a frame with a bad magic."""
    from websockets.asyncio.server import serve

    async def peer(ws):
        await ws.send(json.dumps({"type": "hello", "versions": [1], "session": "x", "latency_us": {}}))
        await ws.recv()  # the subscribe
        await ws.send(json.dumps({"type": "subscribed"}))
        await ws.send(b"XX" + bytes(60))
        await ws.wait_closed()

    async def go():
        async with serve(peer, "127.0.0.1", 0) as server:
            port = server.sockets[0].getsockname()[1]
            async with AsyncClient(f"http://127.0.0.1:{port}").stream() as s:
                with pytest.raises(P.ProtocolError, match="bad magic"):
                    async for _ in s.frames():
                        pass

    run(go())


def test_decoded_outputs_come_named_from_the_hello(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=2)) as (addr, _):
        with Client(f"http://{addr}") as tr:
            tr.wait_ready(30)
            sub = Subscription(taxels=[1], streams=["decoded"], decoders=["force", "texture"])
            with tr.stream(sub) as s:
                outs = take(s.decoded(), 12)
                names = [d["name"] for d in s.hello["streams"]["decoded"]["decoders"]]
    assert {"force", "texture"} <= {o.name for o in outs} and {"force", "texture"} <= set(names)
    force = [o for o in outs if o.name == "force"]
    assert all(o.outputs == ["force_N"] and o.values.shape[1:] == (1, 1) and o.taxels.tolist() == [1] for o in force)
    steps = np.concatenate([o.t_us for o in force])
    assert steps.size and np.all(steps % 32_000 == 0) and np.isfinite(np.concatenate([o.values.ravel() for o in force])).all()
    texture = [o for o in outs if o.name == "texture"]
    assert all(len(o.outputs) == o.values.shape[2] >= 2 for o in texture)  # one probability per label


def test_a_decoded_frame_is_named_whatever_shape_the_hello_gives_its_decoders():
    """A hello is input like any other: decoders in a shape they should not have leave the frame named
    by its index (``#i``), not an exception that would end a bridge."""
    from touchreal_client import AsyncStream

    frame = P.DecodedFrame(P.Header(kind=P.KIND_DECODED), 1, np.array([0], np.uint16), np.array([32_000], np.uint64),
                           np.zeros((1, 1, 1), np.float32))
    stream = AsyncStream("ws://127.0.0.1:9/v1/stream", Subscription())
    for hello in ({}, {"streams": []}, {"streams": {"decoded": 3}}, {"streams": {"decoded": {"decoders": "x"}}},
                  {"streams": {"decoded": {"decoders": [{}, "force"]}}}, {"streams": {"decoded": {"decoders": [{}, {"outputs": 5}]}}}):
        stream.hello = hello
        out = stream.name_decoded(frame)
        assert (out.name, out.outputs) == ("#1", []), hello
    stream.hello = {"streams": {"decoded": {"decoders": [{}, {"name": "force", "outputs": ["force_N"]}]}}}
    assert (stream.name_decoded(frame).name, stream.name_decoded(frame).outputs) == ("force", ["force_N"])


def test_the_client_places_spikes_on_its_own_clock(tmp_path):
    """to_local / spike_latency_us / summary().spike_us against a real server, as a robot would use them:
    each spike's cause lands before its receipt and within the class's stated latency + an update + slack."""
    from server_harness import running_server
    from touchreal_client import Client

    with running_server(tmp_path) as (addr, svc), Client(f"http://{addr}") as tr, tr.stream() as s:
        s.sync_clock()
        lat, frames = [], 0
        for f in s.spikes():
            if f.t_us.size:
                v = s.spike_latency_us(f)
                if v.size:
                    lat.append((f, v))
                    frames += 1
            if frames >= 40:
                break
        summary = s.latency.summary()
        hello = s.hello
    stated = hello["latency_us"]
    for f, v in lat:
        for k, c in enumerate(("SA1", "RA", "PC")):
            sel = f.cls == k
            if sel.any():
                local = s.to_local(f.t_us[sel].astype(float) - hello["delay_us"][c])
                assert np.allclose(f.header.recv_us - local, v[sel])
                assert v[sel].min() >= -2000 and v[sel].max() <= stated[c] + hello["update_us"] + 60_000
    assert set(summary.spike_us) and all(p50 <= p95 <= mx for p50, p95, mx in summary.spike_us.values())
