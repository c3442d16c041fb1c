"""/v1/stream against a real uvicorn server on 127.0.0.1 with real WebSocket clients."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest
import websockets
from helpers import synthetic_trial
from server_harness import (collect, connect, covers, hello_and_subscribe, n_spikes, running_server, stall_one_of_two,
                            until)
from touchreal_client import protocol as P

from touchreal.params import default_params
from touchreal.cli import main
from touchreal.recording import write_dataset
from touchreal.server.settings import RuntimeConfig
from touchreal.stream import encode_trial


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


def _spikes(frames):
    return [f for f in frames if isinstance(f, P.SpikesFrame)]


def _channels(frames):
    return [f for f in frames if isinstance(f, P.ChannelsFrame)]


def test_hello_bare_subscribe_and_time_sync(tmp_path):
    with running_server(tmp_path) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                hello, sub = await hello_and_subscribe(ws)
                assert hello["protocol"] == "touchreal.stream" and hello["version"] == P.VERSION == 2 and hello["addresses"] == "taxels"
                assert hello["session"] == svc.session and hello["taxels"][0]["id"] == 0
                assert set(hello["latency_us"]) == {"SA1", "RA", "PC"} and hello["update_us"] == 32000
                assert sub["taxels"] is None and sub["classes"] == ["SA1", "RA", "PC"] and sub["encoding"] == "binary"
                frames = _spikes(await collect(ws, 30.0, covers(3.0), what="3 s of the stream"))
                await ws.send(json.dumps({"type": "time", "id": 7, "t0_us": 123}))
                reply = next(m for m in await collect(ws, 10.0, lambda fs: any(isinstance(x, dict) for x in fs),
                                                      what="the time reply")
                             if isinstance(m, dict))
                return frames, reply

        frames, reply = run(go())
    assert len(frames) >= 30  # about 31 updates per second
    seqs = [f.header.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and all(f.header.dropped == 0 for f in frames)
    t = np.concatenate([f.t_us for f in frames]).astype(np.int64)
    c = np.concatenate([f.cls for f in frames])
    assert t.size > 0 and all(np.all(np.diff(t[c == k]) >= 0) for k in range(3))  # each class in time order
    for prev, f in zip(frames, frames[1:]):  # finality: nothing arrives before the class's previous final_us
        for k, cls in enumerate(P.CLASSES):
            assert np.all(f.t_us[f.cls == k] >= prev.final_us[cls])
    assert {c for f in frames for c in f.cls.tolist()} <= {0, 1, 2}
    assert all(f.header.params_rev == 1 and f.header.sent_us >= f.header.emit_us for f in frames)
    assert reply["type"] == "time" and reply["id"] == 7 and reply["t0_us"] == 123
    assert reply["t1_us"] <= reply["t2_us"]


def test_subscription_filters_and_changes_what_is_computed(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=4)) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, taxels=[1, 2], classes=["SA1"], encoding="json")
                first = _spikes(await collect(ws, 30.0, covers(2.0), what="2 s of the stream"))
                demand = dict(svc.hub.demand.columns)
                await ws.send(json.dumps({"type": "subscribe", "classes": ["PC"], "taxels": [3]}))
                # the frames of the new subscription (PC final) over 2 s of the stream
                second = _spikes(await collect(ws, 30.0, covers(2.0, where=_pc_final), what="2 s of PC frames"))
                return first, demand, second

        first, demand, second = run(go())
    assert demand == {"SA1": (1, 2)}
    assert first and all(set(f.cls.tolist()) <= {0} and set(f.taxel.tolist()) <= {1, 2} for f in first)
    assert all(f.final_us["RA"] is None and f.final_us["SA1"] is not None for f in first)
    late = [f for f in second if f.final_us["PC"] is not None]
    assert late and all(set(f.cls.tolist()) <= {2} and set(f.taxel.tolist()) <= {3} for f in late)


def _pc_final(frame) -> bool:
    return isinstance(frame, P.SpikesFrame) and frame.final_us["PC"] is not None


def test_nothing_is_computed_while_nobody_is_subscribed(tmp_path):
    with running_server(tmp_path) as (addr, svc):

        async def go():
            rt = svc.runtime
            await until(lambda: rt.state == "idle" and rt.encoder is not None, 10, "the runtime idles")
            idle = rt.state, rt.encoder.active, rt.encoder.running
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, classes=["SA1"])
                frames = _spikes(await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 1, what="the first frame"))
                busy = rt.state, rt.encoder.active
            await until(lambda: rt.state == "idle", 10, "the runtime idles again once the client left")
            return idle, frames, busy, (rt.state, rt.encoder.active, rt.encoder.running)

        idle, frames, busy, after = run(go())
    off = {"singletact": False, "pvdf_filter": False, "pvdf_windows": (), "blocks": 0}
    assert idle == ("idle", {}, off) and after == ("idle", {}, off)  # no branch runs: acquisition only
    assert busy == ("running", {"SA1": (0,)})
    # a returning subscriber waits for no warm-up: SA1 is final to within its latency from the first frame
    assert frames[0].final_us["SA1"] > 0


def _replay_dataset(tmp_path):
    trials = {"a": synthetic_trial(seed=0), "b": synthetic_trial(seed=1, freq_hz=400.0)}
    entries = [{"id": i, "protocol": "ramp", "condition": "c", "repeat": r, "params": {}, "onset_s": 0.3,
                "stim_end_s": 1.05} for r, i in enumerate(trials)]
    write_dataset(tmp_path / "ds", {"name": "t", "trials": entries}, trials)
    return tmp_path / "ds", trials


def _replayed_trains(addr, svc, n_trials):
    """Spikes of every replayed trial, per class, in us on the trial's own clock."""

    async def go():
        async with connect(addr) as ws:
            await hello_and_subscribe(ws)
            return await collect(ws, 30.0, lambda fs: svc.runtime.state == "ended", what="the replay's end")

    frames = _spikes(run(go()))
    # trial boundaries: the source's segment offsets, in the order played
    t = np.concatenate([f.t_us for f in frames]).astype(np.int64)
    c = np.concatenate([f.cls for f in frames])
    return t, c


def test_replay_spikes_equal_touchreal_encode_to_the_microsecond(tmp_path):
    """What a client receives for each replayed trial is what `touchreal encode --clock sensor` writes."""
    ds, trials = _replay_dataset(tmp_path)
    assert main(["encode", str(ds), "--out", str(tmp_path / "enc"), "--clock", "sensor"]) == 0
    with running_server(tmp_path / "state", RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc):
        t, c = _replayed_trains(addr, svc, 2)
        offsets = [0, svc.runtime.source.offset_us]
    assert offsets[1] > 0
    for i, name in enumerate(trials):
        lo = offsets[i]
        hi = offsets[i + 1] if i + 1 < len(offsets) else np.iinfo(np.int64).max
        written = json.loads((tmp_path / "enc" / f"{name}.json").read_text())
        for k, cls in enumerate(P.CLASSES):
            got = t[(c == k) & (t >= lo) & (t < hi)] - lo
            want = np.round(np.array(written[cls]) * 1e6).astype(np.int64)
            assert np.array_equal(got, want[want >= 0]), (name, cls, got[:5], want[:5])


@pytest.mark.shared
def test_replay_of_a_rig_trial_equals_encode(tmp_path, rig):
    entry = rig.entries("ramp")[5]
    with running_server(tmp_path, RuntimeConfig(source=f"replay:{rig.root}:{entry['id']}", speed=10.0)) as (addr, svc):
        t, c = _replayed_trains(addr, svc, 1)
    ref = encode_trial(rig.load(entry), default_params())
    for k, cls in enumerate(P.CLASSES):
        want = np.round(ref[cls] * 1e6).astype(np.int64)
        assert np.array_equal(t[c == k], want[want >= 0]), cls


def test_sensor_clock_runs_past_2_to_the_32_microseconds(tmp_path):
    with running_server(tmp_path, sim_t0_s=2**32 / 1e6 - 0.5) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["spikes", "channels"], channels={"decimation": 50})
                return await collect(ws, 30.0, lambda fs: any((f.final_us["SA1"] or 0) > 2**32 for f in _spikes(fs))
                                     and any(f.t0_us > 2**32 for f in _channels(fs)),
                                     what="spikes and channels past 2**32 us")

        frames = run(go())
    ch = [f for f in frames if isinstance(f, P.ChannelsFrame)]
    finals = [f.final_us["SA1"] for f in _spikes(frames)]
    assert min(finals) < 2**32 < max(finals)
    assert ch and ch[-1].t0_us > 2**32 and ch[0].period_us == 50 * 200
    assert np.isfinite(np.concatenate([f.data for f in ch])).all()


def test_a_channels_only_subscriber_gets_continuous_channels_and_nothing_is_encoded(tmp_path):
    with running_server(tmp_path) as (addr, svc):

        cover = covers(2.0)

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["channels"], channels={"decimation": 25})
                # over 40 channels frames and 2 s of them: no spikes frame came among them
                frames = await collect(ws, 30.0, lambda fs: len(_channels(fs)) > 40 and cover(fs),
                                       what="over 40 channels frames, 2 s of them")
                return frames, svc.runtime.active, svc.runtime.encoder.running

        frames, active, running = run(go())
    ch = [f for f in frames if isinstance(f, P.ChannelsFrame)]
    assert len(ch) > 40 and not _spikes(frames) and active == {}
    assert running["singletact"] and running["pvdf_windows"] == (max(svc.store.active.window_ms(c) for c in P.CLASSES),)
    assert all(b.t0_us == a.t0_us + a.data.shape[0] * a.period_us for a, b in zip(ch, ch[1:]))  # no sample missing
    assert np.isfinite(np.concatenate([f.data for f in ch])).all()


@pytest.mark.parametrize("dense", [True, False], ids=["dense", "activity"])
def test_taxels_nobody_subscribes_to_run_nothing(tmp_path, dense):
    """Dense: a taxel block nobody subscribes to runs nothing. Activity-driven: only the subscribed taxel runs
    (its channels are wanted, so it runs whether a contact woke it or not)."""
    with running_server(tmp_path, RuntimeConfig(taxels=8), taxel_block=4, dense=dense) as (addr, svc):
        cover = covers(2.0)

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, taxels=[5], classes=["SA1"], streams=["spikes", "channels"])
                frames = await collect(ws, 30.0, lambda fs: len(_channels(fs)) > 40 and cover(fs),
                                       what="over 40 channels frames, 2 s of the stream")
                enc = svc.runtime.encoder
                return frames, [(b.pre.running, list(b.taxels)) for b in enc.blocks]

        frames, blocks = run(go())
    if dense:
        assert [bool(r["singletact"]) for r, _ in blocks] == [False, True]  # taxels 0-3: nothing runs
    else:
        assert [taxels for r, taxels in blocks if r["singletact"]] == [[5]]
    ch = [f for f in frames if isinstance(f, P.ChannelsFrame)]
    assert len(ch) > 40 and all(f.taxels.tolist() == [5] and np.isfinite(f.data).all() for f in ch)
    assert all(set(f.taxel.tolist()) <= {5} for f in _spikes(frames))


def test_float32_compute_runs_the_pipeline_in_float32(tmp_path):
    """--compute-dtype float32 reaches the encoder the service runs, and it streams spikes and channels."""
    with running_server(tmp_path, RuntimeConfig(taxels=2), compute_dtype="float32") as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["spikes", "channels"])
                frames = await collect(ws, 20.0, lambda fs: len(_spikes(fs)) >= 10 and len(_channels(fs)) >= 5,
                                       what="10 spikes and 5 channels frames")
                return frames, svc.runtime.encoder.dtype, [b.pre.dtype for b in svc.runtime.encoder.blocks]

        frames, dtype, block_dtypes = run(go())
    assert dtype == np.float32 and all(d == np.float32 for d in block_dtypes)
    assert len(_spikes(frames)) >= 10
    ch = [f for f in frames if isinstance(f, P.ChannelsFrame)]
    assert len(ch) >= 5 and all(np.isfinite(f.data).all() for f in ch)


async def _next_reply(ws) -> dict:
    """The next text message that is not the periodic ``clock``."""
    while (msg := json.loads(await ws.recv()))["type"] == "clock":
        pass
    return msg


def test_malformed_messages_get_errors_and_documented_closes(tmp_path):
    with running_server(tmp_path) as (addr, svc):

        async def go():
            out = {}
            async with connect(addr) as ws:
                json.loads(await ws.recv())
                for bad in ("{", "[1]", '{"type": "subscribe", "classes": ["SA9"]}'):
                    await ws.send(bad)
                    out.setdefault("errors", []).append(await _next_reply(ws))
                await ws.send(b"\x00\x01")
                out["binary"] = await _next_reply(ws)
                await ws.send(json.dumps({"type": "subscribe"}))  # still alive and serving
                out["ok"] = (await _next_reply(ws))["type"]
            async with connect(addr) as ws:
                await ws.recv()
                await ws.send(json.dumps({"type": "subscribe", "version": 99}))
                out["version_error"] = await _next_reply(ws)
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:  # a clock message may come before the close
                        await asyncio.wait_for(ws.recv(), 5)
                out["version_close"] = closed.value.rcvd.code
            async with connect(addr) as ws:
                await ws.recv()
                for _ in range(10):
                    await ws.send("nonsense")
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:
                        await asyncio.wait_for(ws.recv(), 5)
                out["spam_close"] = closed.value.rcvd.code
            async with connect(addr, max_size=None) as ws:
                await ws.recv()
                await ws.send("x" * (P.MAX_CLIENT_MESSAGE_BYTES + 10))
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:  # a clock message may come before the close
                        await asyncio.wait_for(ws.recv(), 5)
                out["big_close"] = closed.value.rcvd.code
            return out

        out = run(go())
        alive = httpx.get(f"http://{addr}/v1/health").status_code
    assert [e["code"] for e in out["errors"]] == ["bad_message"] * 3
    assert "SA9" in out["errors"][2]["message"] and "binary" in out["binary"]["message"]
    assert out["ok"] == "subscribed"
    assert out["version_error"]["code"] == "unsupported_version" and out["version_close"] == P.CLOSE_UNSUPPORTED_VERSION
    assert out["spam_close"] == P.CLOSE_TOO_MANY_ERRORS
    assert out["big_close"] == P.CLOSE_TOO_BIG
    assert alive == 200


def test_stalled_client_is_dropped_and_others_are_unaffected(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=16), queue_frames=48, slow_timeout_s=0.5) as (addr, svc):

        frames, rcvd, gone = run(stall_one_of_two(addr, svc.hub, svc.metrics, 30.0))
        kicked = svc.metrics.kicked._value.get()
    assert rcvd is not None and rcvd.code == P.CLOSE_SLOW_CONSUMER and "slow consumer" in rcvd.reason
    assert kicked == 1 and gone
    seqs = [f.header.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and frames[-1].header.dropped == 0


def test_updates_an_overloaded_loop_drops_are_seq_gaps_every_client_sees(tmp_path):
    """The event loop stalls (0.8 s of 5 ms hops > MAX_BACKLOG): the updates the service drops rather
    than queue reach no client, and each client's seq jumps by exactly that many, counted in dropped."""
    import time

    with running_server(tmp_path) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["spikes"])
                frames = _spikes(await collect(ws, 30.0, covers(1.0), what="1 s of the stream"))
                svc.loop.call_soon_threadsafe(time.sleep, 0.8)  # the server's loop, not ours
                cover = covers(2.0)
                # the overload counted, its gap seen, and the stream on for 2 s (stall included) since
                after = await collect(ws, 30.0, lambda fs: cover(fs) and svc.metrics.overload._value.get() > 0
                                      and _has_gap(frames + _spikes(fs)), what="the stall's drops, then 2 s of the stream")
                return frames + _spikes(after)

        frames = run(go())
        lost = int(svc.metrics.overload._value.get())
        # every frame dropped for the one client, whatever the reason (the overload's, or on a loaded machine
        # a frame its own queue dropped as stale)
        client = int(sum(x.value for m in svc.metrics.drops.collect() for x in m.samples if x.name.endswith("_total")))
    assert lost > 0
    seqs, updates = np.array([f.header.seq for f in frames]), np.array([f.header.update for f in frames])
    dropped = np.array([f.header.dropped for f in frames])
    gaps = np.diff(seqs) - 1
    at = np.flatnonzero(gaps)  # the stall's gap (a loaded machine may add one of its own)
    assert len(at) >= 1 and np.all(gaps >= 0) and gaps.sum() == client >= lost  # the gaps are exactly the losses
    assert np.array_equal(np.diff(updates)[at] - 1, gaps[at])  # where the lost updates were
    assert dropped[0] == 0 and np.array_equal(dropped[at + 1] - dropped[at], gaps[at]) and dropped[-1] == client


def _has_gap(frames) -> bool:
    """Whether the frames' seq jumps anywhere."""
    return any(b.header.seq != a.header.seq + 1 for a, b in zip(frames, frames[1:]))


def test_many_subscribers_lose_nothing(tmp_path):
    n = 25
    # the 25 clients share this process (and its GIL) with the server: a frame can wait more than the
    # default 250 ms age limit here, which would drop it by design (test_a_slow_reader_... covers that)
    with running_server(tmp_path, max_frame_age_ms=2000) as (addr, svc):

        async def one():
            cover = covers(3.0)  # a predicate per client
            async with connect(addr) as ws:
                await hello_and_subscribe(ws)
                return _spikes(await collect(ws, 60.0, lambda fs: len(fs) > 40 and cover(fs),
                                             what="over 40 frames, 3 s of the stream"))

        async def go():
            return await asyncio.gather(*(one() for _ in range(n)))

        results = run(go())
        rendered = svc.hub.frames_rendered
        updates = svc.runtime.update_no
    for frames in results:
        seqs = [f.header.seq for f in frames]
        assert len(frames) > 40 and seqs == list(range(len(seqs))) and frames[-1].header.dropped == 0
    # the same subscription is rendered once per update, whatever the number of subscribers
    assert rendered <= updates
    # every subscriber got the same spikes for the updates they share
    common = set.intersection(*({f.header.update for f in fr} for fr in results))
    by_update = [{f.header.update: f.t_us.tolist() for f in fr} for fr in results]
    assert all(b[u] == by_update[0][u] for b in by_update for u in common)


def test_parameter_upload_while_streaming_swaps_between_updates(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        new = default_params().model_copy(deep=True)
        new.classes["SA1"].tau_ms = new.classes["SA1"].tau_ms * 1.5

        async def go():
            async with connect(addr) as ws, httpx.AsyncClient(base_url=f"http://{addr}") as http:
                await hello_and_subscribe(ws)
                before = _spikes(await collect(ws, 30.0, covers(1.0), what="1 s of the stream"))
                r = await http.put("/v1/params", json=json.loads(new.to_json()))
                cover = covers(1.5)
                after = _spikes(await collect(ws, 30.0, lambda fs: cover(fs) and any(
                    isinstance(f, P.SpikesFrame) and f.header.params_rev == 2 for f in fs),
                    what="frames of revision 2, and 1.5 s of the stream"))
                return before, r, after

        before, r, after = run(go())
    assert r.status_code == 200 and r.json()["rev"] == 2
    revs = [f.header.params_rev for f in before + after]
    assert revs == sorted(revs) and set(revs) == {1, 2}
    first_new = next(f for f in after if f.header.params_rev == 2)
    assert "params_changed" in first_new.header.flag_names()
    assert sum("params_changed" in f.header.flag_names() for f in before + after) == 1


def test_permessage_deflate_only_when_the_client_asks(tmp_path):
    with running_server(tmp_path) as (addr, svc):

        async def go():
            out = []
            for compression in (None, "deflate"):
                async with connect(addr, compression=compression) as ws:
                    out.append(ws.response.headers.get("Sec-WebSocket-Extensions"))
                    await hello_and_subscribe(ws)
            return out

        plain, deflate = run(go())
    assert plain is None and deflate is not None and "permessage-deflate" in deflate


def test_nan_and_inf_from_the_source_are_repaired_flagged_and_counted(tmp_path):
    trial = synthetic_trial(seed=3)
    trial.st[40:45] = np.nan
    trial.pvdf[500:520] = np.inf
    trial.pvdf[900] = -np.inf
    entries = [{"id": "bad", "protocol": "ramp", "condition": "c", "repeat": 0, "params": {}, "onset_s": 0.3, "stim_end_s": 1.05}]
    write_dataset(tmp_path / "ds", {"name": "t", "trials": entries}, {"bad": trial})
    with running_server(tmp_path / "state", RuntimeConfig(source=f"replay:{tmp_path / 'ds'}", speed=4.0)) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws, streams=["spikes", "channels"], channels={"decimation": 5})
                return await collect(ws, 20.0, lambda fs: svc.runtime.state == "ended", what="the replay's end")

        frames = run(go())
        faults = httpx.get(f"http://{addr}/v1/status").json()["faults"]
        assert httpx.get(f"http://{addr}/v1/health").status_code == 200
    assert faults["singletact_non_finite"] == 5 and faults["pvdf_non_finite"] == 21
    assert any("source_gap" in f.header.flag_names() for f in _spikes(frames))
    data = np.concatenate([f.data for f in frames if isinstance(f, P.ChannelsFrame)])
    assert data.size and np.isfinite(data).all()


def test_each_class_goes_out_as_soon_as_it_is_final(tmp_path):
    """SA1 and RA on a 16 ms window are final ~100 ms before PC on 128 ms; the hello says so."""
    params = default_params().model_copy(deep=True)
    params.version = 3
    for c in ("SA1", "RA"):
        params.classes[c].window_ms = 16.0
    path = tmp_path / "fast.json"
    params.save(path)
    with running_server(tmp_path / "state", params=path) as (addr, svc):

        async def go():
            async with connect(addr) as ws:
                hello, sub = await hello_and_subscribe(ws)
                return hello, sub, _spikes(await collect(ws, 30.0, covers(3.0), what="3 s of the stream"))

        hello, sub, frames = run(go())
    lat = hello["latency_us"]
    assert lat["SA1"] < 25000 and lat["RA"] < 25000 and lat["PC"] > 100000 and sub["latency_us"] == lat
    assert hello["window_us"] == {"SA1": 16000, "RA": 16000, "PC": 128000}
    # every frame: SA1's samples are complete far beyond PC's (final_us includes each class's delay)
    shift = 1000 * (params.classes["SA1"].delay_ms - params.classes["PC"].delay_ms)
    start = next(f.final_us["SA1"] for f in frames if f.final_us["SA1"])  # past the stream start (hum estimate)
    lead = [f.final_us["SA1"] - f.final_us["PC"] - shift for f in frames if f.final_us["SA1"] > start + 300_000]
    assert min(lead) > 60000


@pytest.mark.slow  # ~16 s of a reader that stops reading; .ci/run runs it (pytest -m slow)
def test_a_slow_reader_gets_no_backlog_and_is_closed_as_slow(tmp_path):
    """A client that reads 10 frames/s of a stream of hundreds: frames older than max_frame_age_ms are
    dropped in the server's queue (counted as stale), so no frame it receives waited there longer;
    the bytes in flight beyond the queue are bounded by the connection's send buffer (send_buffer_bytes),
    not the kernel's autotuning; once its sender has taken no frame for slow_timeout_s it is closed 4008."""
    import socket

    with running_server(tmp_path, RuntimeConfig(taxels=4), max_frame_age_ms=250, send_buffer_bytes=65536,
                        slow_timeout_s=2.0) as (addr, svc):
        host, port = addr.split(":")

        async def go():
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.connect((host, int(port)))
            frames, sizes, in_flight, code = [], [], 0, None
            async with connect(addr, sock=sock, max_size=None) as ws:
                await hello_and_subscribe(ws, streams=["spikes", "channels"], channels={"decimation": 1})
                try:
                    while True:
                        msg = await asyncio.wait_for(ws.recv(), 30)
                        if isinstance(msg, bytes):
                            frames.append(P.decode_frame(msg))
                            sizes.append(len(msg))
                            if svc.hub.subscribers:
                                sub = next(iter(svc.hub.subscribers.values()))
                                in_flight = max(in_flight, sub.sent - len(frames))
                        await asyncio.sleep(0.1)  # the stimulus, not a wait: this client reads 10 frames/s
                except websockets.ConnectionClosed as closed:
                    code = closed.rcvd.code if closed.rcvd else None
            return frames, sizes, in_flight, code

        frames, sizes, in_flight, code = run(go())
        stale = svc.metrics.drops.labels("stale")._value.get()
        kicked = svc.metrics.kicked._value.get()
    waited = np.array([(f.header.sent_us - f.header.emit_us) / 1000 for f in frames])
    assert code == P.CLOSE_SLOW_CONSUMER and kicked == 1 and stale > 0
    assert len(frames) >= 20 and waited.max() <= 250 + 50, waited.max()  # its age in the server's queue
    seqs = [f.header.seq for f in frames]
    assert sum(b - a - 1 for a, b in zip(seqs, seqs[1:])) == frames[-1].header.dropped - frames[0].header.dropped
    assert in_flight * np.mean(sizes) <= 1 << 20, (in_flight, np.mean(sizes))  # autotuning lets megabytes queue
