"""The sans-I/O parts of the NATS bridge: loss counting on the broker hop, forwarded demand, Hub.skip."""

from __future__ import annotations

import numpy as np
import pytest
from touchreal_client import protocol as P

from touchreal.bridge import subjects
from touchreal.bridge.demand import Announced, ForwardedDemand, Rejected, announcement, parse_announcement
from touchreal.bridge.settings import GatewaySettings
from touchreal.bridge.subjects import check_sensor_id
from touchreal.bridge.upstream import UpstreamTracker, update_from_frame
from touchreal.server.hub import Hub


def test_tracker_counts_seq_jumps_resyncs_and_new_sessions():
    tr = UpstreamTracker()
    assert tr.observe("a", 5).new_session and tr.lost == 0  # joining mid-stream is no loss
    assert tr.observe("a", 6).lost == 0
    assert tr.observe("a", 9).lost == 2
    assert tr.observe("a", 3).lost == 0  # behind: the publisher restarted its count, resync
    assert tr.observe("a", 4).lost == 0
    seen = tr.observe("b", 0)
    assert seen.new_session and seen.lost == 0 and tr.sessions == 2
    assert tr.observe("b", 2**32 - 2).lost == 0  # far behind, not 4 billion lost: resync
    tr.observe("b", 2**32 - 1)
    assert tr.observe("b", 1).lost == 1 and tr.lost == 3  # seq wraps like the u32 header field


def test_published_frames_become_hub_updates():
    h = P.Header(P.KIND_SPIKES, update=7, emit_us=1000, params_rev=2, flags=P.FLAG_RESTARTED)
    raw = P.encode_spikes(h, np.array([10, 20], np.uint64), np.array([0, 1], np.uint16), np.array([0, 2], np.uint8),
                          {"SA1": 30, "RA": None, "PC": 25})
    upd = update_from_frame(P.decode_frame(raw), 2)
    assert (upd.update, upd.params_rev, upd.flags, upd.emit_us, upd.spikes) == (7, 2, P.FLAG_RESTARTED, 1000, True)
    assert upd.final_us == {"SA1": 30, "PC": 25} and upd.t_us.tolist() == [10, 20]
    data = np.arange(3 * 1 * 4, dtype=np.float32).reshape(3, 1, 4)
    raw = P.encode_channels(P.Header(P.KIND_CHANNELS, update=7), 200 * 1001 + 50, 200, [1], data)
    upd = update_from_frame(P.decode_frame(raw), 2)
    assert not upd.spikes and upd.channels.k0 == 1001 and upd.offset_us == 50
    assert np.isnan(upd.channels.data[:, 0]).all() and np.array_equal(upd.channels.data[:, 1], data[:, 0])
    values = np.arange(2 * 1 * 3, dtype=np.float32).reshape(2, 1, 3)
    raw = P.encode_decoded(P.Header(P.KIND_DECODED, update=8, emit_us=900), 4, [1], np.array([5, 6], np.uint64), values)
    with pytest.raises(ValueError, match="decoder's name"):
        update_from_frame(P.decode_frame(raw), 2)
    upd = update_from_frame(P.decode_frame(raw), 2, "force")
    (name, taxels, t_us, vals), = upd.decoded
    assert not upd.spikes and upd.channels is None and (upd.update, upd.emit_us) == (8, 900)
    assert (name, taxels, t_us.tolist()) == ("force", (1,), [5, 6]) and np.array_equal(vals, values)


def test_demand_announcements_merge_into_one_product_and_expire():
    d, ttl = parse_announcement("g1", announcement("g1", Announced({"SA1": [2, 0]}, [1]), ttl_s=2.0))
    assert (dict(d.columns), list(d.channels), ttl) == ({"SA1": [0, 2]}, [1], 2.0)
    fd = ForwardedDemand()
    fd.announce("g1", d, ttl, now=0.0)
    fd.announce("g2", Announced({"PC": [3]}), 5.0, now=0.0)
    s = fd.spikes()
    assert (s.taxels, s.classes, s.streams) == ([0, 2, 3], ["SA1", "PC"], ["spikes"])
    c = fd.channels()
    assert (c.taxels, c.streams, c.decimation) == ([1], ["channels"], 1)
    fd.expire(now=2.5)
    assert fd.gateways == ["g2"] and fd.channels() is None and fd.spikes().classes == ["PC"]
    fd.announce("g2", Announced({}), 5.0, now=3.0)  # an empty announcement withdraws at once
    assert fd.spikes() is None and fd.gateways == []
    # decoders: one decoded-only subscription per decoder, over the union of its taxels; no spikes
    d, ttl = parse_announcement("g3", announcement("g3", Announced({}, (), {"force": [3, 1], "texture": []})))
    assert dict(d.decoders) == {"force": [1, 3]} and not d.empty
    fd.announce("g3", d, ttl, now=4.0)
    fd.announce("g4", Announced({}, (), {"force": [0], "texture": [2]}), ttl, now=4.0)
    assert fd.spikes() is None and fd.channels() is None
    dec = fd.decoded()
    assert {n: (s.taxels, s.classes, s.streams, s.decoders) for n, s in dec.items()} == {
        "force": ([0, 1, 3], [], ["decoded"], ["force"]), "texture": ([2], [], ["decoded"], ["texture"])}
    assert parse_announcement("old", b'{"gateway": "old", "ttl_ms": 5, "columns": {"RA": [0]}}')[0].decoders == {}
    for bad in (b"{", b"[]", b'{"gateway": 1, "ttl_ms": 5, "columns": {}}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {"XX": [0]}}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "channels": [-1]}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "decoders": {"a.b": [0]}}',  # not a subject token
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "decoders": {"force": 0}}'):
        with pytest.raises(ValueError, match="malformed demand"):
            parse_announcement("g", bad)


def test_sensor_ids_are_single_subject_tokens():
    assert check_sensor_id("lab-1_a") == "lab-1_a"
    for bad in ("", "a.b", "a b", "*", ">", "x" * 65):
        with pytest.raises(ValueError, match="sensor id"):
            check_sensor_id(bad)


def test_hub_skip_advances_seq_and_dropped_per_stream_and_decoder():
    hub = Hub(capacity=4, slow_timeout_s=1.0)
    hub.configure(2, P.CLASSES, {"force": ["SA1"], "texture": ["SA1", "RA"]})
    both, spikes, none, force, every = hub.add(), hub.add(), hub.add(), hub.add(), hub.add()
    hub.subscribe(both, P.Subscription(streams=["spikes", "channels"]))
    hub.subscribe(spikes, P.Subscription())
    hub.subscribe(force, P.Subscription(taxels=[1], streams=["decoded"], decoders=["force"]))
    hub.subscribe(every, P.Subscription(streams=["spikes", "decoded"]))  # decoders None: every decoder
    hub.skip(3, "spikes")
    hub.skip(2, "channels")
    hub.skip(4, "decoded", "texture")
    hub.skip(1, "decoded", "force")
    assert [(s.seq, s.dropped) for s in (both, spikes, none, force, every)] == [(5, 5), (3, 3), (0, 0), (1, 1), (8, 8)]


def test_announcements_are_bounded_and_the_gateway_count_is_capped():
    from touchreal.bridge.demand import MAX_ANNOUNCEMENT_BYTES

    def reason(data: bytes, n_taxels: int = 4, sender: str = "g") -> str:
        with pytest.raises(Rejected) as exc:
            parse_announcement(sender, data, n_taxels)
        return exc.value.reason

    assert reason(b" " * (MAX_ANNOUNCEMENT_BYTES + 1)) == "oversized"
    assert reason(announcement("g", Announced({"SA1": [4]}))) == "out_of_range"
    assert reason(announcement("g", Announced({}, [0], {"force": [9]}))) == "out_of_range"
    assert reason(announcement("g", Announced({"SA1": [0]}), ttl_s=61.0)) == "malformed"
    assert reason(announcement("a.b", Announced({"SA1": [0]})), sender="a.b") == "malformed"
    assert reason(b"[" * 5000 + b"]" * 5000) == "malformed"
    fd = ForwardedDemand(max_gateways=2)
    fd.announce("a", Announced({"SA1": [0]}), 1.0, now=0.0)
    fd.announce("b", Announced({"RA": [1]}), 5.0, now=0.0)
    with pytest.raises(Rejected) as exc:
        fd.announce("c", Announced({"PC": [2]}), 5.0, now=0.5)
    assert exc.value.reason == "too_many_gateways" and fd.gateways == ["a", "b"]
    fd.announce("a", Announced({"SA1": [3]}), 1.0, now=0.5)  # a live gateway may always renew
    fd.announce("c", Announced({"PC": [2]}), 5.0, now=2.0)  # a's announcement expired: room for c
    assert fd.gateways == ["b", "c"]


def test_a_large_skins_demand_is_announced_as_id_ranges_within_the_bound():
    from touchreal.bridge.demand import MAX_ANNOUNCEMENT_BYTES

    every = range(65536)
    data = announcement("g", Announced({c: every for c in P.CLASSES}, every, {"force": every}))
    assert len(data) < 400  # 4 x 65,536 ids as single ids took about 1.6 MB, over the 256 kB bound
    d, _ = parse_announcement("g", data, 65536)
    assert all(list(d.columns[c]) == list(every) for c in P.CLASSES) and list(d.decoders["force"]) == list(every)
    # ranges may overlap and mix with single ids (a gateway from before ranges); the set is what counts
    d, _ = parse_announcement("g", b'{"gateway": "g", "ttl_ms": 5, "columns": {"RA": [[2, 5], [3, 7], 9, [9, 9]]}}', 10)
    assert d.columns["RA"] == [2, 3, 4, 5, 6, 9]
    for bad, why in ((b'{"gateway": "g", "ttl_ms": 5, "columns": {"RA": [[5, 2]]}}', "malformed"),
                     (b'{"gateway": "g", "ttl_ms": 5, "columns": {"RA": [[0, 1, 2]]}}', "malformed"),
                     (b'{"gateway": "g", "ttl_ms": 5, "columns": {"RA": [[0, 65537]]}}', "malformed"),
                     (b'{"gateway": "g", "ttl_ms": 5, "columns": {"RA": [[0, 11]]}}', "out_of_range")):
        with pytest.raises(Rejected) as exc:
            parse_announcement("g", bad, 10)
        assert exc.value.reason == why, bad
    assert P.id_ranges([5, 0, 1, 2, 2, 9]) == [[0, 3], [5, 6], [9, 10]] and P.id_ranges([]) == []


def test_a_frame_over_the_brokers_max_payload_crosses_in_parts_and_a_broken_one_is_dropped_and_counted():
    from touchreal.bridge.parts import HEADROOM_BYTES, MAX_PARTS, Reassembler, split

    room = 4096 - HEADROOM_BYTES
    frame = bytes(range(256)) * 40  # 10,240 bytes: 4 parts of at most `room`
    pieces = split(frame, 4096)
    assert [h for h, _ in pieces] == ["1/4", "2/4", "3/4", "4/4"] and all(len(b) <= room for _, b in pieces)
    assert split(b"small", 4096) == [(None, b"small")]
    with pytest.raises(ValueError, match="parts"):
        split(b"x" * (room * MAX_PARTS + 1), 4096)
    r = Reassembler()
    got = [r.push("s", h, b) for h, b in pieces]
    assert got[:3] == [None] * 3 and got[3] == frame and r.dropped == 0 and r.pending_bytes == 0
    # subjects are put together apart; a whole frame passes straight through
    other = split(b"y" * 5000, 4096)
    assert r.push("t", *other[0]) is None and r.push("s", None, b"whole") == b"whole" and r.push("t", *other[1]) == b"y" * 5000
    # a lost part: the frame begun is given up (counted), the next one is whole again
    assert [r.push("s", h, b) for h, b in (pieces[0], pieces[2], pieces[3])] == [None, None, None] and r.dropped == 1
    assert [r.push("s", h, b) for h, b in pieces][-1] == frame
    # joined mid-frame: its tail is counted once; a new first part restarts; a bad header is an error
    assert [r.push("s", h, b) for h, b in pieces[2:]] == [None, None] and r.dropped == 2
    r.push("s", *pieces[0])
    assert r.push("s", *pieces[0]) is None and r.dropped == 3  # a first part again: the one begun is dropped
    for bad in ("0/4", "5/4", "x/4", "1/999", "3"):
        with pytest.raises(ValueError):
            r.push("s", bad, b"")
    assert r.pending_bytes == 0 and r.dropped == 4


def test_an_announcement_counts_for_the_gateway_whose_subject_it_came_on_only():
    silence = announcement("victim", Announced({}))
    with pytest.raises(Rejected) as exc:  # on the attacker's own subject, naming its victim: dropped
        parse_announcement("attacker", silence)
    assert exc.value.reason == "identity_mismatch"
    assert parse_announcement("victim", silence)[0].empty  # the victim itself may withdraw
    sub = subjects.demand("lab-1", "gw-1")
    assert sub == "touchreal.lab-1.demand.gw-1" and subjects.last_token(sub) == "gw-1"
    assert subjects.gateway_permissions("gw-1")["publish"][0] == sub.replace("lab-1", "*")
    assert not any("demand" in s for s in subjects.gateway_permissions("gw-1")["subscribe"])


def test_one_identity_holds_one_place_and_a_restarted_gateway_renews_its_own_when_all_are_taken():
    fd = ForwardedDemand(max_gateways=2)
    for i in range(100):  # one identity announcing over and over: one place, its latest demand
        fd.announce("flooder", Announced({"SA1": [i % 4]}), 60.0, now=i * 0.2)
    fd.announce("gw-2", Announced({"RA": [0]}), 3.0, now=20.0)
    assert fd.gateways == ["flooder", "gw-2"] and fd.spikes().taxels == [0, 3]
    # gw-2 crashed (its announcement lives on) and came back under its id: it renews, though all places are taken
    fd.announce("gw-2", Announced({"PC": [1]}), 3.0, now=20.5)
    assert fd.gateways == ["flooder", "gw-2"] and fd.spikes().classes == ["SA1", "PC"]
    with pytest.raises(Rejected) as exc:  # a new identity still finds no room
        fd.announce("newcomer", Announced({"RA": [0]}), 3.0, now=21.0)
    assert exc.value.reason == "too_many_gateways"


def test_a_gateways_default_id_is_stable_per_host_and_port_and_a_subject_token():
    a, b = GatewaySettings(port=8801), GatewaySettings(port=8801)
    assert a.gateway_id == b.gateway_id and a.gateway_id.endswith("-8801") and subjects.token_ok(a.gateway_id)
    assert GatewaySettings(port=8802).gateway_id != a.gateway_id
    assert GatewaySettings(port=0).gateway_id != GatewaySettings(port=0).gateway_id  # any free port: no stable id
    assert GatewaySettings(gateway_id="gateway-1").gateway_id == "gateway-1"
    with pytest.raises(ValueError, match="gateway id"):
        GatewaySettings(gateway_id="a.b")
