"""The stream's clock model: :mod:`touchreal_client.clock` (sans-I/O) and the service's ``clock`` and
refreshed ``hello`` messages on a real server (and through a gateway), with real WebSocket clients."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import pytest
from server_harness import collect, connect, hello_and_subscribe, running_server
from touchreal_client import protocol as P
from touchreal_client.clock import ClockMap, ClockPoint

from touchreal.params import default_params


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 90))


def now_us() -> int:
    return time.time_ns() // 1000


# -- sans-I/O -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [
    {"sensor_us": 1, "wall_us": 2, "rate": 1.0, "error_us": 0},  # no epoch
    {"sensor_us": -1, "wall_us": 2, "rate": 1.0, "error_us": 0, "epoch": 0},
    {"sensor_us": True, "wall_us": 2, "rate": 1.0, "error_us": 0, "epoch": 0},
    {"sensor_us": 1, "wall_us": 2, "rate": float("nan"), "error_us": 0, "epoch": 0},
    {"sensor_us": 1, "wall_us": 2, "rate": 0, "error_us": 0, "epoch": 0},
    {"sensor_us": 1.5, "wall_us": 2, "rate": 1.0, "error_us": 0, "epoch": 0},
    [1, 2, 3],
])
def test_a_malformed_clock_is_refused(bad):
    with pytest.raises(ValueError):
        ClockPoint.from_json(bad)


def test_clock_map_maps_each_segment_with_its_own_point_and_applies_the_offset():
    cm = ClockMap()
    with pytest.raises(LookupError):
        cm.to_local_us(0)
    assert cm.update(None) is None
    cm.update({"type": "clock", "sensor_us": 1_000_000, "wall_us": 5_000_000, "rate": 1.0, "error_us": 0, "epoch": 0})
    cm.update(ClockPoint(2_000_000, 6_000_000, 1.0, 0, 0))
    # a replayed trial at 2x speed starts at wire time 10 s, acquired at wall 7 s
    cm.update(ClockPoint(10_000_000, 7_000_000, 0.5, 0, 1))
    assert cm.to_server_wall_us(1_500_000) == 5_500_000
    assert cm.to_server_wall_us(2_036_500) == 6_036_500  # a flushed spike of the first segment keeps its point
    assert cm.to_server_wall_us(11_000_000) == 7_500_000  # second segment at rate 0.5
    assert cm.to_server_wall_us(500_000) == 4_500_000  # before every point: the oldest one
    np.testing.assert_array_equal(cm.to_server_wall_us(np.array([1_500_000, 11_000_000])), [5_500_000, 7_500_000])
    cm.set_offset(250.0, 40.0)
    assert cm.to_local_us(1_500_000) == 5_500_000 - 250.0 and cm.error_us() == 40.0
    assert cm.update(ClockPoint(3_000_000, 1, 1.0, 0, 0)) is None  # an older epoch is ignored
    assert cm.update(ClockPoint(9_000_000, 1, 1.0, 0, 1)) is None  # backwards within an epoch is ignored
    cm.update(ClockPoint(0, 9_000_000, 1.0, 0, 2))  # a new epoch restarting the wire clock lower: history restarts
    assert cm.points == [ClockPoint(0, 9_000_000, 1.0, 0, 2)]


# -- a real server ----------------------------------------------------------------------------------------
async def _stream(addr: str, seconds: float, **sub) -> tuple[dict, ClockMap, list[tuple[P.SpikesFrame, int]], list[dict]]:
    """Connect, subscribe, and keep every spikes frame with this client's receive time (us) and every
    clock message, mapping with a ClockMap as a client written from the docs would.

    A fixed window of ``seconds``, on purpose: the tests count the clock messages it brings (a rate,
    ">= 1 Hz"), which only a stretch of wall time can show."""
    async with connect(addr) as ws:
        hello = json.loads(await ws.recv())
        cm, clocks, frames = ClockMap(), [], []
        cm.update(hello["clock"])
        await ws.send(json.dumps({"type": "subscribe", **sub}))
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                msg = await asyncio.wait_for(ws.recv(), max(end - time.monotonic(), 0.01))
            except asyncio.TimeoutError:
                break
            recv = now_us()
            if isinstance(msg, bytes):
                f = P.decode_frame(msg)
                if isinstance(f, P.SpikesFrame) and f.t_us.size:
                    frames.append((f, recv))
                continue
            m = json.loads(msg)
            if m["type"] == "clock":
                clocks.append(m)
                cm.update(m)
        return hello, cm, frames, clocks


def _latencies(hello: dict, cm: ClockMap, frames) -> dict[str, np.ndarray]:
    """Per class: receipt minus the mapped acquisition of each spike's causing sample (ms)."""
    out: dict[str, list[np.ndarray]] = {}
    for f, recv in frames:
        for k, c in enumerate(P.CLASSES):
            t = f.t_us[f.cls == k].astype(np.float64)
            if t.size:
                out.setdefault(c, []).append((recv - cm.to_local_us(t - hello["delay_us"][c])) / 1000.0)
    return {c: np.concatenate(v) for c, v in out.items()}


def test_the_first_client_of_a_fresh_server_places_every_spike_after_its_cause(tmp_path):
    """Connected before the first sample: hello's clock is null or a real point, clock messages follow
    at >= 1 Hz, and every spike's receipt comes after its mapped cause, by no more than the class's
    stated latency plus an update and some slack (the old anchor put stamps 4.3 s off)."""
    with running_server(tmp_path) as (addr, svc):

        async def go():
            return await asyncio.gather(_stream(addr, 4.0, classes=["SA1"]), _stream(addr, 4.0, classes=["PC"]))

        (h1, cm1, f1, c1), (h2, cm2, f2, c2) = run(go())
    for hello, cm, frames, clocks in ((h1, cm1, f1, c1), (h2, cm2, f2, c2)):
        assert hello["clock"] is None or ClockPoint.from_json(hello["clock"]).rate == 1.0
        assert len(clocks) >= 3 and frames  # >= 1 Hz over the stream
        walls = np.array([m["wall_us"] - m["sensor_us"] for m in clocks])  # sim: one straight line, rate 1
        assert np.ptp(walls) <= 1 and all(m["rate"] == 1.0 for m in clocks)
        lat = _latencies(hello, cm, frames)
        update_ms = hello["update_us"] / 1000
        for c, v in lat.items():
            stated = hello["latency_us"][c] / 1000
            assert v.min() >= -2.0, (c, v.min())  # never before its cause (2 ms: the clock's target error)
            assert v.max() <= stated + update_ms + 60.0, (c, v.max(), stated)
    # whatever each client subscribes to, both map with the same model
    assert cm1.last.wall_us - cm1.last.sensor_us == pytest.approx(cm2.last.wall_us - cm2.last.sensor_us, abs=1)


def test_the_clock_point_is_when_the_chunk_was_in_hand(tmp_path):
    """Independent check of the sim's model: each update's point (its chunk's end instant S acquired at
    W) against the moment the acquisition thread had that chunk (``acq_us``, read after ``next_chunk``,
    which includes the skin simulation's own compute, 0.5-5 ms): never earlier, and a model that were
    systematically early would show in the cheapest chunk, which is in hand within 2 ms."""
    seen = []
    with running_server(tmp_path) as (addr, svc):
        publish = svc.hub.publish

        def spy(upd):
            seen.append((upd.acq_us, upd.clock))
            publish(upd)

        svc.hub.publish = spy

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, classes=["SA1"])
                await collect(ws, 30.0, lambda fs: len(seen) >= 60, what="60 updates")

        run(go())
    err = np.array([acq - clock.wall_us for acq, clock in seen]) / 1000.0
    assert err.size >= 60 and -0.1 <= err.min() <= 2.0, (err.min(), np.median(err))


def test_a_new_hello_follows_a_parameter_upload_and_a_window_change(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        base = f"http://{addr}"

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, classes=["SA1"])
                p = default_params()
                p.classes["SA1"].delay_ms += 1.0
                async with httpx.AsyncClient() as http:
                    r = await http.put(base + "/v1/params", json=json.loads(p.to_json()))
                    assert r.status_code == 200, r.text
                    got = await collect(ws, 10.0, lambda fs: any(isinstance(x, dict) and x.get("type") == "hello" for x in fs),
                                        what="a new hello")
                    first = next(x for x in got if isinstance(x, dict) and x.get("type") == "hello")
                    r = await http.patch(base + "/v1/config", json={"window_ms": 64})
                    assert r.status_code == 200, r.text
                    got = await collect(ws, 15.0, lambda fs: any(isinstance(x, dict) and x.get("type") == "hello"
                                                                 and x["window_us"]["PC"] == 64000 for x in fs),
                                        what="a hello with the 64 ms window")
                    second = next(x for x in got if isinstance(x, dict) and x.get("type") == "hello"
                                  and x["window_us"]["PC"] == 64000)
                    r = await http.post(base + "/v1/params/rollback", json={"rev": 1})
                    assert r.status_code == 200, r.text
                    rev = r.json()["rev"]  # a rollback is recorded as a new revision
                    got = await collect(ws, 10.0, lambda fs: any(isinstance(x, dict) and x.get("type") == "hello"
                                                                 and x["params"]["rev"] == rev for x in fs),
                                        what=f"a hello of revision {rev}")
                    assert any(isinstance(x, dict) and x.get("type") == "hello" and x["params"]["rev"] == rev
                               and x["window_us"]["PC"] == 128000 for x in got)
                return first, second

        first, second = run(go())
    assert first["params"]["rev"] == 2
    assert first["delay_us"]["SA1"] == int(round((default_params().classes["SA1"].delay_ms + 1.0) * 1000))
    assert second["params"]["rev"] == 3 and second["latency_us"]["PC"] < first["latency_us"]["PC"]


@pytest.mark.slow
def test_clock_messages_pass_through_a_gateway_unchanged(tmp_path, nats_url):
    from test_bridge_nats import gateway, publishing

    with publishing(tmp_path, nats_url) as (_, svc, _pub), gateway(nats_url) as (gw_addr, gw):

        async def go():
            return await _stream(gw_addr, 4.0, classes=["SA1", "RA"])

        hello, cm, frames, clocks = run(go())
        direct = svc.clock
    assert hello["server"].startswith("touchreal-gateway") and hello["delay_us"]
    assert len(clocks) >= 2 and frames
    # the gateway's clients map with the service's own model: the same line (sim: rate 1)
    assert all(m["wall_us"] - m["sensor_us"] == direct.wall_us - direct.sensor_us for m in clocks)
    lat = _latencies(hello, cm, frames)
    assert all(v.min() >= -2.0 for v in lat.values()), {c: v.min() for c, v in lat.items()}


def test_a_replay_states_its_speed_and_a_new_epoch_for_each_trial(tmp_path):
    """Replayed at 4x: rate 0.25 wall us per sensor us; each trial's wire offset begins a new epoch, and
    within an epoch the points lie on one line (a trial is played at a steady pace)."""
    from test_server_stream import _replay_dataset

    from touchreal.server.settings import RuntimeConfig

    ds, trials = _replay_dataset(tmp_path)
    with running_server(tmp_path / "state", RuntimeConfig(source=f"replay:{ds}", speed=4.0)) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws)
                clocks: list[dict] = []
                await collect(ws, 30.0, lambda fs: svc.runtime.state == "ended", clock=clocks, what="the replay's end")
                return clocks

        clocks = run(go())
    points = [ClockPoint.from_json(m) for m in clocks]
    assert {p.rate for p in points} == {0.25}
    epochs = sorted({p.epoch for p in points})
    assert len(epochs) >= len(trials), epochs  # a trial, or a resume after waiting for the subscriber
    for e in epochs:
        same = [p for p in points if p.epoch == e]
        lines = [p.wall_us - p.sensor_us * 0.25 for p in same]
        assert max(lines) - min(lines) <= 2.0  # rounding of the us stamps only
    starts = [min(p.sensor_us for p in points if p.epoch == e) for e in epochs]
    assert starts == sorted(starts)  # the wire clock keeps increasing across trials
