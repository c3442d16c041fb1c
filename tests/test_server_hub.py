"""The fan-out hub and demand, sans-I/O: rendering once per subscription, drops, slow consumers."""

from __future__ import annotations

import asyncio
import json
import re

import numpy as np
from touchreal_client import protocol as P

from touchreal.server.demand import build_demand
from touchreal.server.hub import Hub, Subscriber
from touchreal.server.runtime import Update


def _update(n: int = 1) -> Update:
    t = np.arange(3, dtype=np.uint64) + 1000 * n
    return Update(n, 1, 0, 0, 5, t, np.array([0, 1, 2], np.uint16), np.array([0, 1, 2], np.uint8),
                  {"SA1": 2000 * n, "RA": 2000 * n, "PC": 1000 * n})


def test_demand_is_the_union_limited_to_allowed_classes_and_existing_taxels():
    subs = [P.Subscription(taxels=[0, 9], classes=["SA1"]), P.Subscription(taxels=None, classes=["RA", "PC"]),
            P.Subscription(taxels=[2], streams=["channels"]), P.Subscription(taxels=[1], streams=["decoded"], decoders=["force"])]
    d = build_demand(subs, 4, ["SA1", "RA"], {"force": ["SA1", "RA"], "texture": ["PC"]})
    assert d.columns == {"SA1": (0, 1), "RA": (0, 1, 2, 3)}
    assert d.channel_taxels == (2,) and d.decoders == {"force": (1,)}
    assert d.spikes == {"SA1": (0,), "RA": (0, 1, 2, 3)}  # taxel 1's SA1 is computed for the decoder only
    assert build_demand([], 4, ["SA1"], {}).empty


def test_publish_renders_once_per_distinct_subscription_and_filters():
    async def go():
        hub = Hub(capacity=4, slow_timeout_s=1.0)
        hub.configure(3, P.CLASSES, {})
        subs = [hub.add() for _ in range(5)]
        for s in subs[:4]:
            hub.subscribe(s, P.Subscription())
        hub.subscribe(subs[4], P.Subscription(taxels=[1], classes=["RA"], encoding="json"))
        hub.publish(_update())
        return hub, subs

    hub, subs = asyncio.run(go())
    assert hub.frames_rendered == 2
    full = P.decode_frame(subs[0].queue[0].payload)
    assert full.t_us.tolist() == [1000, 1001, 1002] and full.final_us["PC"] == 1000
    text, _ = subs[4].render(subs[4].queue[0])
    one = P.frame_from_json(json.loads(text))
    assert one.taxel.tolist() == [1] and one.final_us == {"SA1": None, "RA": 2000, "PC": None}


def test_a_full_queue_drops_counts_and_finally_kicks_the_subscriber():
    now = [0.0]

    async def go():
        sub = Subscriber(1, capacity=2, slow_timeout_s=1.0, clock=lambda: now[0], max_age_s=None)
        for i in range(4):
            sub.offer(P.KIND_SPIKES, b"x")
        assert (len(sub.queue), sub.dropped, sub.seq, sub.kick) == (2, 2, 4, None)
        sub.queue.popleft()
        sub.offer(P.KIND_SPIKES, b"y")  # room again: accepted, the full period ends
        assert sub.full_since is None and [q.seq for q in sub.queue] == [1, 4]
        sub.offer(P.KIND_SPIKES, b"z")
        now[0] = 1.5
        sub.offer(P.KIND_SPIKES, b"z")
        return sub

    sub = asyncio.run(go())
    assert sub.kick is not None and sub.kick[0] == P.CLOSE_SLOW_CONSUMER and sub.kicked.is_set()
    assert sub.dropped == 4


def test_a_frame_older_than_the_max_age_is_dropped_not_sent():
    now, drops = [0.0], []

    async def go():
        sub = Subscriber(1, capacity=100, slow_timeout_s=1.0, clock=lambda: now[0], max_age_s=0.25,
                         on_drop=lambda reason, n: drops.append((reason, n)))
        for i in range(3):  # queued at 0, 0.1 and 0.2 s
            sub.offer(P.KIND_SPIKES, bytes([i]))
            now[0] += 0.1
        now[0] = 0.36  # the first two are now older than 0.25 s
        first = sub.next_frame()
        return sub, first

    sub, first = asyncio.run(go())
    assert first is not None and first.seq == 2 and first.payload == bytes([2])  # the fresh one, seq 0 and 1 skipped
    assert sub.dropped == 2 and drops == [("stale", 1), ("stale", 1)] and sub.next_frame() is None
    unlimited = Subscriber(2, capacity=4, slow_timeout_s=1.0, clock=lambda: 100.0, max_age_s=None)
    unlimited.offer(P.KIND_SPIKES, b"x")
    unlimited.clock = lambda: 1e6
    assert unlimited.next_frame() is not None and unlimited.dropped == 0


def test_control_replies_are_bounded_by_count_and_bytes():
    async def go():
        by_count = Subscriber(1, capacity=2, slow_timeout_s=1.0)
        for i in range(P.CONTROL_QUEUE_MESSAGES):
            by_count.say(f'{{"type":"time","id":{i}}}')
        assert by_count.kick is None and len(by_count.control) == P.CONTROL_QUEUE_MESSAGES
        by_count.pop_control()  # the sender took one: room for one more
        by_count.say("{}")
        assert by_count.kick is None
        by_count.say("{}")
        assert by_count.kick[0] == P.CLOSE_FLOODING and by_count.kicked.is_set()
        assert len(by_count.control) == P.CONTROL_QUEUE_MESSAGES  # the overflowing reply was not queued
        by_bytes = Subscriber(2, capacity=2, slow_timeout_s=1.0)
        big = "x" * (P.CONTROL_QUEUE_BYTES // 3)
        for _ in range(3):
            by_bytes.say(big)
        assert by_bytes.kick is None and by_bytes.control_chars == 3 * len(big)
        by_bytes.say("x" * (P.CONTROL_QUEUE_BYTES - 3 * len(big) + 1))
        assert by_bytes.kick[0] == P.CLOSE_FLOODING
        assert by_bytes.pop_control() == big and by_bytes.control_chars == 2 * len(big)

    asyncio.run(go())


def test_admit_fills_a_bare_subscribe_with_what_is_served_and_refuses_what_is_not():
    hub = Hub(capacity=4, slow_timeout_s=1.0)
    assert hub.admit({"type": "subscribe", "taxels": [40]}).taxels == [40]  # unconfigured (gateway before hello)
    hub.configure(4, ["PC"], {"texture": ["PC"]})
    bare = hub.admit({"type": "subscribe"})
    assert bare.classes == ["PC"] and bare.taxels is None
    for msg, fragment in [({"classes": ["SA1", "PC"]}, r"classes \['SA1'\] are not served"),
                          ({"taxels": [1, 4, 70000 - 5000]}, r"taxels \[4, 65000\] do not exist"),
                          ({"streams": ["decoded"], "decoders": ["force"]}, r"decoders \['force'\] are not offered")]:
        try:
            hub.admit({"type": "subscribe", **msg})
        except P.ProtocolError as exc:
            assert exc.code == "not_served" and re.search(fragment, str(exc)), str(exc)
        else:
            raise AssertionError(f"{msg} was admitted")
    # a subscription made before the served classes shrank asks for nothing that is not served
    hub.subscribe(hub.add(), P.Subscription(classes=["SA1", "PC"]))
    hub.subscribe(hub.add(), P.Subscription(taxels=[2, 9]))
    assert hub.demand.columns == {"PC": (0, 1, 2, 3)}


def test_a_spikes_frame_with_nothing_new_for_a_subscription_is_not_sent():
    """Updates come every hop: a subscriber gets a spikes frame when its classes' final_us moved, a
    spike of its own arrived or a flag is set; never a frame that repeats what it already has."""
    def hop(n: int, final: dict[str, int], cls: int | None = None, flags: int = 0) -> Update:
        t = np.array([] if cls is None else [final["SA1"] - 1], np.uint64)
        c = np.array([] if cls is None else [cls], np.uint8)
        return Update(n, 1, flags, 0, 5, t, np.zeros(t.size, np.uint16), c, final)

    async def go():
        hub = Hub(capacity=64, slow_timeout_s=1.0)
        hub.configure(1, P.CLASSES, {})
        fast, slow, both = hub.add(), hub.add(), hub.add()
        hub.subscribe(fast, P.Subscription(classes=["SA1", "RA"]))
        hub.subscribe(slow, P.Subscription(classes=["PC"]))
        hub.subscribe(both, P.Subscription())
        updates = [
            hop(1, {"SA1": 5000, "RA": 5000, "PC": 0}),  # first: everyone learns the finals
            hop(2, {"SA1": 10000, "RA": 10000, "PC": 0}),  # the fast classes moved
            hop(3, {"SA1": 15000, "RA": 15000, "PC": 32000}),  # PC's update
            hop(4, {"SA1": 15000, "RA": 15000, "PC": 32000}),  # nothing moved
            hop(5, {"SA1": 15000, "RA": 15000, "PC": 32000}, cls=2),  # a PC spike
            hop(6, {"SA1": 15000, "RA": 15000, "PC": 32000}, flags=P.FLAG_SOURCE_GAP),  # a flag
        ]
        for u in updates:
            hub.publish(u)
        return [[P.decode_frame(q.payload).header.update for q in s.queue] for s in (fast, slow, both)]

    fast, slow, both = asyncio.run(go())
    assert fast == [1, 2, 3, 6]
    assert slow == [1, 3, 5, 6]
    assert both == [1, 2, 3, 5, 6]


def test_a_region_subscription_gets_exactly_its_taxels_in_frames_and_in_the_demand():
    """A 128 x 128 skin (16,384 taxels, 10 mm pitch): a rectangle and an id range resolve to the taxels in
    them, which the demand computes and the frames carry; nothing else."""
    n, cols = 16384, 128
    xy = np.stack([(np.arange(n) % cols - 63.5) * 10.0, (np.arange(n) // cols - 63.5) * 10.0], axis=1)
    rect = (-100.0, 100.0, 0.0, 50.0)  # x in [-100, 100], y in [0, 50] mm: 20 columns of 5 rows
    in_rect = {i for i in range(n) if rect[0] <= xy[i, 0] <= rect[1] and rect[2] <= xy[i, 1] <= rect[3]}
    want = sorted(in_rect | set(range(16000, 16384)))
    assert len(in_rect) == 100

    async def go():
        hub = Hub(capacity=8, slow_timeout_s=1.0, refresh_s=0.0)  # the demand follows at once
        hub.configure(n, P.CLASSES, {"force": ["SA1", "RA"]}, xy)
        sub = hub.add()
        msg = {"type": "subscribe", "classes": ["SA1", "PC"], "streams": ["spikes", "channels", "decoded"],
               "region": {"ranges": [[16000, 16384]], "rects": [{"x_mm": [rect[0], rect[1]], "y_mm": [rect[2], rect[3]]}]}}
        s = hub.admit(msg)
        assert s.taxels is None and s.region is not None and s.to_json()["region"]["ranges"] == [[16000, 16384]]
        hub.subscribe(sub, s)
        spiking = np.arange(0, n, 3)  # a third of the skin spikes in every class
        t = np.repeat(np.arange(3, dtype=np.uint64) + 5000, spiking.size)
        upd = Update(1, 1, 0, 0, 5, t, np.tile(spiking, 3).astype(np.uint16), np.repeat(np.arange(3), spiking.size).astype(np.uint8),
                     {"SA1": 6000, "RA": 6000, "PC": 6000},
                     decoded=[("force", tuple(range(n)), np.array([6000], np.uint64), np.ones((1, n, 1), np.float32))])
        hub.publish(upd)
        return hub, sub

    hub, sub = asyncio.run(go())
    assert hub.demand.columns["SA1"] == tuple(want) and hub.demand.columns["PC"] == tuple(want)
    assert hub.demand.columns["RA"] == tuple(want)  # for the force decoder only
    assert hub.demand.spikes == {"SA1": tuple(want), "PC": tuple(want)} and hub.demand.channel_taxels == tuple(want)
    assert hub.demand.decoders == {"force": tuple(want)}
    spikes, decoded = (P.decode_frame(q.payload) for q in sub.queue)
    assert sorted(set(spikes.taxel.tolist())) == [t for t in want if t % 3 == 0] and set(spikes.cls.tolist()) == {0, 2}
    assert decoded.taxels.tolist() == want


def test_admit_refuses_regions_beyond_the_skin_or_its_known_positions():
    hub = Hub(capacity=4, slow_timeout_s=1.0)
    hub.configure(100, P.CLASSES, {})  # no positions known (a gateway)
    rect = {"x_mm": [0, 1], "y_mm": [0, 1]}
    for region, fragment in [({"ranges": [[90, 101]]}, r"region.ranges \[\[90, 101\]\] reach past"),
                             ({"rects": [rect]}, "need the taxel positions")]:
        try:
            hub.admit({"type": "subscribe", "region": region})
        except P.ProtocolError as exc:
            assert exc.code == "not_served" and re.search(fragment, str(exc)), str(exc)
        else:
            raise AssertionError(f"{region} was admitted")
    hub.configure(100, P.CLASSES, {}, np.zeros((100, 2)))
    hub.configure(100, ["SA1"], {})  # the served classes changed: the positions stay
    assert hub.admit({"type": "subscribe", "region": {"rects": [rect]}}).region.rects == ((0.0, 1.0, 0.0, 1.0),)
    hub.configure(P.MAX_TAXELS, ["SA1"], {})  # another skin: its positions are not those
    assert hub.positions_mm is None
    try:
        hub.admit({"type": "subscribe", "streams": ["channels"]})
    except P.ProtocolError as exc:
        assert exc.code == "not_served" and "at most 65535 taxels" in str(exc)
    else:
        raise AssertionError("a channels frame of 65,536 taxels was admitted")
    assert hub.admit({"type": "subscribe", "streams": ["channels"], "region": {"ranges": [[1, P.MAX_TAXELS]]}})
