"""Live fan-out through a real nats-server on 127.0.0.1: service -> publisher -> NATS -> gateways -> clients.

Each test starts Debian's ``nats-server`` on a free loopback port (skips with the reason when the
binary is missing; .ci/run installs it), the service under uvicorn with the publisher, and
gateways under uvicorn, all on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from server_harness import (collect, connect, covers, hello_and_subscribe, needs_nats_server, stall_one_of_two, until,
                            wait_until)
from test_server_stream import _replay_dataset
from touchreal_client import protocol as P

from touchreal.bridge import natsd, subjects
from touchreal.bridge.auth import NatsAuth
from touchreal.bridge.gateway import Gateway, create_gateway_app
from touchreal.bridge.settings import GatewaySettings
from touchreal.bridge.publisher import NatsPublisher
from touchreal.params import default_params
from touchreal.server.app import serving, serving_app
from touchreal.server.service import Service
from touchreal.server.settings import RuntimeConfig, ServeSettings
from touchreal.stream import encode_trial

SENSOR = "lab-1"


@contextmanager
def publishing(state_dir: Path, url: str, config: RuntimeConfig | None = None, publisher: dict | None = None,
               **settings):
    """The service on a free loopback port, publishing to NATS as SENSOR; yields (addr, service, publisher)."""
    svc = Service(ServeSettings(host="127.0.0.1", port=0, state_dir=state_dir, **settings), config or RuntimeConfig())
    pub = NatsPublisher(svc, url, SENSOR, **(publisher or {}))
    with serving(svc, companions=[pub]) as addr:
        yield addr, svc, pub


@contextmanager
def gateway(url: str, port: int = 0, auth: NatsAuth | None = None, **settings) -> Iterator[tuple[str, Gateway]]:
    """A gateway on 127.0.0.1 that has the publisher's hello; yields (addr, gateway)."""
    gw = Gateway(GatewaySettings(nats=url, sensor_id=SENSOR, host="127.0.0.1", port=port, **settings), auth)
    with serving_app(create_gateway_app(gw), port=port) as addr:
        wait_until(lambda: gw.ready()[0], 10, lambda: f"the gateway is ready: {gw.ready()[1]}")
        yield addr, gw


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


def _spikes(frames):
    return [f for f in frames if isinstance(f, P.SpikesFrame)]


def _consecutive(frames) -> bool:
    seqs = [f.header.seq for f in frames]
    return seqs == list(range(seqs[0], seqs[0] + len(seqs)))


def _has_gap(frames) -> bool:
    """Whether the frames' seq jumps anywhere."""
    return any(b.header.seq != a.header.seq + 1 for a, b in zip(frames, frames[1:]))


def _shared(via: list, direct: list, kind: type) -> int:
    """How many frames of ``kind`` in ``via`` carry an update the ``direct`` ones carry too."""
    updates = {f.header.update for f in direct if isinstance(f, kind)}
    return sum(isinstance(f, kind) and f.header.update in updates for f in via)


def test_frames_arrive_in_order_through_two_gateways_and_demand_is_forwarded(tmp_path, nats_url):
    with publishing(tmp_path, nats_url, RuntimeConfig(taxels=4)) as (addr, svc, pub), \
            gateway(nats_url) as (ga, g1), gateway(nats_url) as (gb, g2):

        async def go():
            async with connect(ga) as w1, connect(gb) as w2, connect(addr) as direct:
                h1, _ = await hello_and_subscribe(w1, taxels=[0, 2], classes=["SA1", "PC"])
                h2, _ = await hello_and_subscribe(w2, streams=["spikes", "channels"])  # everything
                await hello_and_subscribe(direct, streams=["spikes", "channels"])
                await until(lambda: len(pub.demand.gateways) == 2, 10, "both gateways' demand reached the publisher")
                await until(lambda: dict(svc.hub.demand.columns) == {c: (0, 1, 2, 3) for c in P.CLASSES}, 10,
                            "the service computes the union of both")
                f1, f2, fd = [], [], []
                spans = [covers(3.0) for _ in range(3)]

                def enough(_) -> bool:  # 3 s of the stream on each, over 60 frames of each kind both ways
                    return (all(c(fs) for c, fs in zip(spans, (f1, f2, fd))) and len(_spikes(f1)) > 60
                            and _shared(f2, fd, P.ChannelsFrame) > 60 and _shared(f2, fd, P.SpikesFrame) > 60)

                await asyncio.gather(*(collect(ws, 60.0, enough, into=fs, what="3 s of frames, over 60 shared ones")
                                       for ws, fs in ((w1, f1), (w2, f2), (direct, fd))))
            # the gateways withdraw their demand as soon as their clients leave: the publisher no longer subscribes
            await until(lambda: not pub.demand.gateways, 10, "the gateways withdrew their demand")
            return h1, h2, f1, f2, fd, [s.subscription for s in pub.lanes.values()]

        h1, h2, f1, f2, fd, after = run(go())
    # channels (decimation 25 of the 5 kHz grid) through the gateway equal the service's own
    ch_direct = {f.header.update: f for f in fd if isinstance(f, P.ChannelsFrame)}
    ch_gw = [f for f in f2 if isinstance(f, P.ChannelsFrame) and f.header.update in ch_direct]
    assert len(ch_gw) > 60
    for f in ch_gw:
        d = ch_direct[f.header.update]
        assert (f.t0_us, f.period_us) == (d.t0_us, d.period_us) and np.array_equal(f.taxels, d.taxels)
        assert np.array_equal(f.data, d.data)
    assert _consecutive(f2)  # spikes and channels frames share the client's seq
    f2, fd = _spikes(f2), _spikes(fd)
    assert h1["session"] == h2["session"] == svc.session and len(h1["taxels"]) == 4
    assert set(h1["streams"]) == {"spikes", "channels", "decoded"} and "gateway" in h1["server"]
    assert after == [None, None]
    f1 = _spikes(f1)
    assert _consecutive(f1)
    for frames in (f1, f2):
        assert len(frames) > 60 and frames[-1].header.dropped == 0
        ups = [f.header.update for f in frames]
        # in order; an update with nothing new for the subscription sends no frame (seq shows none was lost)
        assert all(b > a for a, b in zip(ups, ups[1:]))
        assert all(f.header.sent_us >= f.header.emit_us for f in frames)
    assert all(set(f.cls.tolist()) <= {0, 2} and set(f.taxel.tolist()) <= {0, 2} for f in f1)
    assert all(f.final_us["RA"] is None and f.final_us["SA1"] is not None for f in f1)
    # the same update carries the same spikes whichever way it travelled
    direct = {f.header.update: f for f in fd}
    shared = [f for f in f2 if f.header.update in direct]
    assert len(shared) > 60 and sum(f.t_us.size for f in shared) > 0
    for f in shared:
        d = direct[f.header.update]
        assert np.array_equal(f.t_us, d.t_us) and np.array_equal(f.taxel, d.taxel) and np.array_equal(f.cls, d.cls)
        assert f.final_us == d.final_us and f.header.emit_us == d.header.emit_us


def test_replayed_trials_through_a_gateway_equal_touchreal_encode(tmp_path, nats_url):
    ds, trials = _replay_dataset(tmp_path)
    with publishing(tmp_path / "state", nats_url, RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc, _), \
            gateway(nats_url) as (ga, _gw):
        assert svc.runtime.state == "waiting"  # the replay holds still until a gateway forwards demand

        async def go():
            async with connect(ga) as ws:
                await hello_and_subscribe(ws)
                return _spikes(await collect(ws, 30.0, lambda fs: svc.runtime.state == "ended", what="the replay's end"))

        frames = run(go())
        offsets = [0, svc.runtime.source.offset_us]
    assert _consecutive(frames) and frames[-1].header.dropped == 0
    t = np.concatenate([f.t_us for f in frames]).astype(np.int64)
    c = np.concatenate([f.cls for f in frames])
    for i, trial in enumerate(trials.values()):
        lo, hi = offsets[i], (offsets[i + 1] if i + 1 < len(offsets) else np.iinfo(np.int64).max)
        ref = encode_trial(trial, default_params())
        for k, cls in enumerate(P.CLASSES):
            want = np.round(ref[cls] * 1e6).astype(np.int64)
            assert np.array_equal(t[(c == k) & (t >= lo) & (t < hi)] - lo, want[want >= 0]), (i, cls)


def test_stalled_gateway_client_is_dropped_without_delaying_others(tmp_path, nats_url):
    with publishing(tmp_path, nats_url, RuntimeConfig(taxels=16)) as (addr, svc, _), \
            gateway(nats_url, queue_frames=48, slow_timeout_s=0.5) as (ga, gw):

        frames, rcvd, gone = run(stall_one_of_two(ga, gw.hub, gw.metrics, 30.0))
        lost = gw.upstream.lost + gw.upstream_channels.lost
    assert rcvd is not None and rcvd.code == P.CLOSE_SLOW_CONSUMER and gone
    ch = [f for f in frames if isinstance(f, P.ChannelsFrame)]
    assert len(frames) > 100 and _consecutive(frames) and frames[-1].header.dropped == lost == 0
    assert ch and ch[0].period_us == 200 and ch[0].data.shape[1:] == (16, 4) and np.isfinite(ch[-1].data).all()


def test_slow_nats_subscriber_drops_become_gaps_the_client_sees(tmp_path, nats_url):
    with publishing(tmp_path, nats_url) as (addr, svc, pub), gateway(nats_url, pending_frames=2) as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                await hello_and_subscribe(ws)
                before = _spikes(await collect(ws, 30.0, covers(1.0), what="1 s of the stream"))
                gw.loop.call_soon_threadsafe(time.sleep, 0.8)  # the gateway stalls: ~25 frames pile up in NATS
                cover = covers(2.0)
                # the slow consumer counted, its gap seen, and the stream on for 2 s (stall included) since
                after = _spikes(await collect(ws, 30.0, lambda fs: cover(fs) and gw.m_slow._value.get() > 0
                                              and _has_gap(before + _spikes(fs)),
                                              what="the stall's losses, then 2 s of the stream"))
                return before, after

        before, after = run(go())
        lost, slow = gw.upstream.lost, gw.m_slow._value.get()
        counted = gw.metrics.drops.labels("upstream_loss")._value.get()  # touchreal_dropped_frames_total
    frames = before + after
    seqs = np.array([f.header.seq for f in frames])
    updates = np.array([f.header.update for f in frames])
    assert slow > 0
    # every update lost on the hop is a seq jump, counted in dropped, and nothing else is (an update
    # with nothing new for the subscription, e.g. during the stream start, sends no frame: no seq)
    assert np.all(np.diff(seqs) <= np.diff(updates))
    jumps = int(np.sum(np.diff(seqs) - 1))
    assert 0 < jumps == frames[-1].header.dropped - frames[0].header.dropped <= lost
    assert jumps <= counted <= lost


def _decoded(frames):
    return [f for f in frames if isinstance(f, P.DecodedFrame)]


def _steps(frames) -> set[int]:
    """The steps (us) of the decoded frames among ``frames``."""
    return {int(t) for f in _decoded(frames) for t in f.t_us}


def test_decoded_outputs_cross_nats_on_demand_and_equal_the_service_direct(tmp_path, nats_url):
    with publishing(tmp_path, nats_url, RuntimeConfig(taxels=4)) as (addr, svc, pub), gateway(nats_url) as (ga, gw):

        async def go():
            async with connect(ga) as via, connect(addr) as direct:
                hv, _ = await hello_and_subscribe(via, taxels=[0, 2], streams=["decoded"], decoders=["force"])
                hd, _ = await hello_and_subscribe(direct, taxels=[0, 2], streams=["decoded"], decoders=["force"])
                subject = f"touchreal.{SENSOR}.decoded.force"
                await until(lambda: subject in pub.lanes and pub.lanes[subject].subscription is not None
                            and sorted(svc.runtime.decoders) == ["force"], 10, "the decoder's lane is subscribed")
                lanes = {k: v.subscription for k, v in pub.lanes.items()}
                demand, running = dict(svc.hub.demand.decoders), sorted(svc.runtime.decoders)
                fv, fd = [], []
                spans = covers(3.0), covers(3.0)

                def enough(_) -> bool:  # 3 s of outputs on each, over 60 steps both got
                    return spans[0](fv) and spans[1](fd) and len(_steps(fv) & _steps(fd)) > 60

                await asyncio.gather(collect(via, 60.0, enough, into=fv, what="3 s of outputs, over 60 shared steps"),
                                     collect(direct, 60.0, enough, into=fd, what="3 s of outputs, over 60 shared steps"))
                announced = gw.status()["demand"]
            # both clients gone: the lane idles and the decoder stops
            await until(lambda: pub.lanes[subject].subscription is None and not svc.runtime.decoders, 10,
                        "the lane idles and the decoder stops")
            return hv, hd, lanes, demand, running, fv, fd, announced, pub.lanes, sorted(svc.runtime.decoders)

        hv, hd, lanes, demand, running, fv, fd, announced, after, running_after = run(go())
    names = [d["name"] for d in hv["streams"]["decoded"]["decoders"]]
    assert names == [d["name"] for d in hd["streams"]["decoded"]["decoders"]] and "force" in names
    # only the decoder's lane is subscribed upstream: the SA1/RA spikes it reads are computed, not published
    subject = f"touchreal.{SENSOR}.decoded.force"
    assert lanes[f"touchreal.{SENSOR}.frames"] is None and lanes[f"touchreal.{SENSOR}.channels"] is None
    assert (lanes[subject].taxels, lanes[subject].streams, lanes[subject].decoders) == ([0, 2], ["decoded"], ["force"])
    assert demand == {"force": (0, 2)} and running == ["force"]
    assert announced == {"columns": {}, "channel_taxels": [], "decoders": {"force": [[0, 1], [2, 3]]}}  # id ranges
    assert after[subject].subscription is None and running_after == []
    fv, fd = _decoded(fv), _decoded(fd)
    assert fv and _consecutive(fv) and fv[-1].header.dropped == 0
    assert {f.decoder for f in fv} == {names.index("force")}
    direct = {int(t): f.values[i] for f in fd for i, t in enumerate(f.t_us)}
    via = {int(t): (f.taxels.tolist(), f.values[i]) for f in fv for i, t in enumerate(f.t_us)}
    shared = sorted(set(direct) & set(via))
    assert len(shared) > 60  # 32 ms steps over ~3 s
    for t in shared:  # the same step carries the same force, bit for bit, whichever way it travelled
        taxels, values = via[t]
        assert taxels == [0, 2] and np.array_equal(values, direct[t])


def test_a_decoders_frames_lost_on_the_hop_become_gaps_its_subscribers_see(tmp_path, nats_url):
    with publishing(tmp_path, nats_url) as (addr, svc, pub), gateway(nats_url, pending_frames=2) as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                hello, _ = await hello_and_subscribe(ws, streams=["decoded"], decoders=["force_sa1"])
                before = _decoded(await collect(ws, 30.0, covers(1.0), what="1 s of outputs"))
                gw.loop.call_soon_threadsafe(time.sleep, 0.8)  # the gateway stalls: frames pile up in NATS
                cover = covers(2.0)
                # the stall's gap seen, and the outputs on for 2 s (stall included) since
                after = _decoded(await collect(ws, 30.0, lambda fs: cover(fs) and _has_gap(before + _decoded(fs)),
                                               what="the stall's losses, then 2 s of outputs"))
                return hello, before, after

        hello, before, after = run(go())
        lost = gw.upstream_decoded["force_sa1"].lost
    step = next(d["step_us"] for d in hello["streams"]["decoded"]["decoders"] if d["name"] == "force_sa1")
    frames = before + after
    seq_gaps = np.diff([f.header.seq for f in frames]) - 1
    steps = [np.asarray(f.t_us, np.int64) for f in frames]
    assert all(np.all(np.diff(s) == step) for s in steps)
    step_gaps = np.array([(b[0] - a[-1]) // step - 1 for a, b in zip(steps, steps[1:])])
    # each lost frame is one seq jump counted in dropped, and steps are missing exactly where seq jumps
    assert 0 < seq_gaps.sum() == frames[-1].header.dropped - frames[0].header.dropped <= lost
    assert np.array_equal(step_gaps > 0, seq_gaps > 0) and np.all(step_gaps >= seq_gaps)


@pytest.mark.slow
def test_a_gateway_restarted_mid_stream_resumes_and_others_lose_nothing(tmp_path, nats_url):
    with publishing(tmp_path, nats_url) as (addr, svc, pub), gateway(nats_url) as (gb, _g2):
        port = natsd.free_port()

        async def first_life():
            with gateway(nats_url, port=port) as (ga, g1):
                async with connect(ga) as ws:
                    hello, _ = await hello_and_subscribe(ws)
                    return hello, _spikes(await collect(ws, 30.0, covers(1.5), what="1.5 s of the stream")), g1.id

        async def go():
            async with connect(gb) as steady:
                await hello_and_subscribe(steady)
                got: list = []
                back: list[int] = []  # how many frames the steady client had once the restarted gateway served
                since = covers(1.0)
                # the steady client reads through the whole restart and 1 s of the stream after it (a pause
                # the restart caused shows), and for over 150 frames
                collecting = asyncio.create_task(collect(
                    steady, 60.0, lambda fs: bool(back) and len(fs) > 150 and since(fs[back[0]:]), into=got,
                    what="the restart over, then 1 s of the stream, over 150 frames"))
                h1, f1, id1 = await first_life()  # the gateway goes away with its client...
                await until(lambda: len(pub.demand.gateways) == 1, 10, "the publisher saw it go")
                with gateway(nats_url, port=port) as (ga, g1):  # ...and comes back on the same address
                    async with connect(ga) as ws:
                        h2, _ = await hello_and_subscribe(ws)
                        f2 = _spikes(await collect(ws, 30.0, covers(1.5), what="1.5 s of the stream"))
                        live = pub.demand.gateways
                back.append(len(got))
                return h1, f1, h2, f2, _spikes(await collecting), (id1, g1.id, live)

        h1, f1, h2, f2, steady, (id1, id2, back) = run(go())
    assert id1 == id2 and id1 in back  # the same identity (HOSTNAME-PORT): it renewed its own place
    assert h1["session"] == h2["session"] == svc.session  # same sensor clock: the client carries on
    assert f1 and f2 and _consecutive(f2) and f2[0].header.seq == 0
    assert f2[0].header.update > f1[-1].header.update
    assert f2[0].final_us["SA1"] >= f1[-1].final_us["SA1"]
    assert len(steady) > 150 and _consecutive(steady) and steady[-1].header.dropped == 0
    ups = [f.header.update for f in steady]
    finals = np.array([f.final_us["SA1"] for f in steady])
    # upstream never paused for the restart: in order, SA1's watermark moving on in hops (5-10 ms). A pause
    # the restart caused would last a demand announcement (1 s) or its expiry (3 s); a loaded 2-core CI
    # box has stalled this one process (service, two gateways, client) for 320 ms once, hence 0.5 s
    assert all(b > a for a, b in zip(ups, ups[1:]))
    assert np.diff(finals).max() <= 500_000, np.sort(np.diff(finals))[-5:]


def test_gateway_reports_not_ready_without_a_publisher_and_bad_demand_is_ignored(tmp_path, nats_url):
    import httpx
    import nats

    gw = Gateway(GatewaySettings(nats=nats_url, sensor_id="nobody", host="127.0.0.1", port=0))
    with serving_app(create_gateway_app(gw)) as ga:
        wait_until(lambda: gw.nc is not None and gw.nc.is_connected, 10, "the gateway connected to NATS")
        r = httpx.get(f"http://{ga}/v1/ready")
    assert r.status_code == 503 and "no hello" in r.json()["reason"]

    with publishing(tmp_path, nats_url) as (addr, svc, pub):

        async def go():
            nc = await nats.connect(nats_url)
            for bad in (b"{", b'{"gateway": "x", "ttl_ms": 1000, "columns": {"XX": [0]}}', b'[]'):
                await nc.publish(subjects.demand(SENSOR, "x"), bad)
            await nc.publish(subjects.demand(SENSOR, "rec"), json.dumps(
                {"gateway": "rec", "ttl_ms": 1000, "columns": {"RA": [0]}}).encode())
            await nc.flush()
            await until(lambda: svc.hub.demand.columns == {"RA": (0,)}, 10, "the valid announcement counts")
            await until(lambda: not svc.hub.demand.columns, 10, "its ttl ran out")
            await nc.close()
            return pub.status()["demand_rejected"]

        rejected = run(go())
    assert rejected["malformed"] == 3


def test_a_late_joiner_catches_up_on_the_retained_seconds(tmp_path, nats_js_url):
    import nats
    from nats.js.api import DeliverPolicy, StorageType

    from touchreal.server.runtime import wall_us

    subject = f"touchreal.{SENSOR}.frames"
    with publishing(tmp_path, nats_js_url, RuntimeConfig(taxels=2),
                    publisher={"publish_all": True, "retain_s": 2.0}) as (addr, svc, pub):

        async def go():
            nc = await nats.connect(nats_js_url)
            js = nc.jetstream()

            async def expired():  # the stream's info once its first frames expired
                info = await js.stream_info(f"touchreal_{SENSOR}")
                return info if info.state.first_seq > 1 else None

            # the service has published longer than the retention
            info = await until(expired, 30, "the first retained frames to expire")
            live: list[bytes] = []

            async def on_live(msg):
                live.append(msg.data)

            joined_us = wall_us()
            await nc.subscribe(subject, cb=on_live)  # an ordinary subscriber joining now: live frames only
            late = await js.subscribe(subject, ordered_consumer=True, deliver_policy=DeliverPolicy.ALL)
            caught, caught_seqs = [], set()

            async def caught_up() -> bool:  # one more message; true once it got over 20 of the live ones
                try:
                    msg = await late.next_msg(timeout=0.5)
                except nats.errors.TimeoutError:
                    return False
                caught.append(msg)
                caught_seqs.add(P.decode_header(msg.data).seq)
                return len(live) > 20 and sum(P.decode_header(d).seq in caught_seqs for d in live) > 20

            await until(caught_up, 30, "the late joiner caught up with over 20 live frames", interval=0)
            await nc.close()
            return info, joined_us, live, caught

        info, joined_us, live, caught = run(go())
        status = pub.status()["retain"]
    assert info.config.storage == StorageType.MEMORY and info.config.max_age == 2.0 and status["error"] is None
    frames = [P.decode_frame(m.data) for m in caught]
    assert {m.headers[subjects.SESSION_HEADER] for m in caught} == {svc.session}
    assert _consecutive(frames)  # the stored seconds and the live frames join without a gap
    age_s = (joined_us - frames[0].header.emit_us) / 1e6
    assert 1.5 < age_s < 3.0, age_s  # about the retained 2 s, not the 5 s the service has been publishing
    assert frames[-1].header.emit_us > joined_us and len(live) > 20
    by_seq = {f.header.seq: m.data for f, m in zip(frames, caught)}
    shared = [d for d in live if P.decode_header(d).seq in by_seq]
    assert len(shared) > 20 and all(by_seq[P.decode_header(d).seq] == d for d in shared)  # frames stored unchanged


def test_retention_without_jetstream_is_reported_and_publishing_goes_on(tmp_path, nats_url):
    import httpx

    with publishing(tmp_path, nats_url, publisher={"publish_all": True, "retain_s": 2.0}) as (addr, svc, pub):
        wait_until(lambda: pub.published >= 20, 20, lambda: f"20 frames published; {pub.status()}")
        status = httpx.get(f"http://{addr}/v1/status").json()["nats"]
    assert status["retain"]["seconds"] == 2.0 and "-js" in status["retain"]["error"]
    assert status["connected"] and status["published"] >= 20  # the service's own /v1/status tells


def test_frames_over_the_brokers_max_payload_cross_in_parts_and_equal_the_service_direct(tmp_path):
    """A broker with a 16 kB max_payload (1 MB by default): the full-rate channels of 16 taxels are 41 kB
    per update, so each crosses in parts and the gateway puts it together again, equal to the service's
    own frame; a client sees no gap and the publisher counts the parted frames."""
    needs_nats_server()
    conf = tmp_path / "small.conf"
    conf.write_text("max_payload: 16384\n")
    with natsd.local_nats_server(config=conf) as url, \
            publishing(tmp_path / "svc", url, RuntimeConfig(taxels=16)) as (addr, svc, pub), gateway(url) as (ga, gw):

        async def go():
            async with connect(ga, max_size=None) as via, connect(addr, max_size=None) as direct:
                for ws in (via, direct):
                    await hello_and_subscribe(ws, streams=["spikes", "channels"], channels={"decimation": 1})
                fv, fd = [], []

                def enough(_) -> bool:
                    return _shared(fv, fd, P.ChannelsFrame) > 30 and _shared(fv, fd, P.SpikesFrame) > 30

                await asyncio.gather(*(collect(ws, 60.0, enough, into=fs, what="over 30 shared frames of each kind")
                                       for ws, fs in ((via, fv), (direct, fd))))
                return fv, fd, pub.status(), gw.status()

        fv, fd, pub_status, gw_status = run(go())
    assert pub_status["max_payload"] == 16384 and pub_status["parted"] >= 30 and pub_status["failures"] == 0
    assert gw_status["upstream"]["parted_frames_dropped"] == 0 and gw_status["upstream"]["bad_frames"] == 0
    direct = {(type(f), f.header.update): f for f in fd if isinstance(f, (P.ChannelsFrame, P.SpikesFrame))}
    shared = [f for f in fv if (type(f), f.header.update) in direct]
    assert sum(isinstance(f, P.ChannelsFrame) and f.data.nbytes > 16384 for f in shared) >= 25  # all but a short first one or so
    for f in shared:
        d = direct[(type(f), f.header.update)]
        if isinstance(f, P.ChannelsFrame):
            assert (f.t0_us, f.period_us) == (d.t0_us, d.period_us) and np.array_equal(f.taxels, d.taxels)
            assert np.array_equal(f.data, d.data)
        else:
            assert np.array_equal(f.t_us, d.t_us) and np.array_equal(f.taxel, d.taxel) and np.array_equal(f.cls, d.cls)
    assert _consecutive(fv) and fv[-1].header.dropped == 0


def test_a_population_crosses_nats_and_gateway_demand_is_per_afferent(tmp_path, nats_url):
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"variants": {"SA1": [1.0], "RA": [1.0], "PC": [1.0]}}))
    with publishing(tmp_path / "state", nats_url, RuntimeConfig(taxels=4), population=str(plan)) as (addr, svc, pub), \
            gateway(nats_url) as (ga, gw):
        pop = svc.population
        ra = pop.layout.ids("RA")[:200]

        async def go():
            async with connect(ga) as via, connect(addr) as direct:
                hello, _ = await hello_and_subscribe(via, version=2, taxels=ra.tolist(), classes=["RA"])
                await hello_and_subscribe(direct, version=2, taxels=ra.tolist(), classes=["RA"])
                await until(lambda: set(svc.hub.demand.columns.get("RA", ())) >= set(ra.tolist()), 10,
                            "the gateway's afferent demand reached the service")
                fv, fd = [], []
                enough = lambda _: sum(f.t_us.size for f in _spikes(fv)) >= 30 and _shared(fv, fd, P.SpikesFrame) > 20  # noqa: E731
                await asyncio.gather(collect(via, 60.0, enough, into=fv, what="30 afferent spikes through the gateway"),
                                     collect(direct, 60.0, enough, into=fd, what="the direct stream alongside"))
                return hello, fv, fd

        hello, fv, fd = run(go())
    assert hello["addresses"] == "afferents" and P.hello_afferents(hello).cls.size == len(pop)
    direct = {f.header.update: f for f in _spikes(fd)}
    shared = [f for f in _spikes(fv) if f.header.update in direct]
    assert shared and sum(f.t_us.size for f in shared) > 0
    for f in shared:  # the same afferents' spikes whichever way they travelled
        d = direct[f.header.update]
        assert np.array_equal(f.t_us, d.t_us) and np.array_equal(f.taxel, d.taxel)
        assert set(f.taxel.tolist()) <= set(ra.tolist()) and set(f.cls.tolist()) <= {1}
