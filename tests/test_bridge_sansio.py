"""The sans-I/O parts of the NATS bridge: loss counting on the broker hop, forwarded demand, Hub.skip."""

from __future__ import annotations

import numpy as np
import pytest
from touchreal_client import protocol as P

from touchreal.bridge.demand import Announced, ForwardedDemand, announcement, parse_announcement
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
    gid, d, ttl = parse_announcement(announcement("g1", Announced({"SA1": [2, 0]}, [1]), ttl_s=2.0))
    assert (gid, dict(d.columns), list(d.channels), ttl) == ("g1", {"SA1": [0, 2]}, [1], 2.0)
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
    gid, d, ttl = parse_announcement(announcement("g3", Announced({}, (), {"force": [3, 1], "texture": []})))
    assert dict(d.decoders) == {"force": [1, 3]} and not d.empty
    fd.announce("g3", d, ttl, now=4.0)
    fd.announce("g4", Announced({}, (), {"force": [0], "texture": [2]}), ttl, now=4.0)
    assert fd.spikes() is None and fd.channels() is None
    dec = fd.decoded()
    assert {n: (s.taxels, s.classes, s.streams, s.decoders) for n, s in dec.items()} == {
        "force": ([0, 1, 3], [], ["decoded"], ["force"]), "texture": ([2], [], ["decoded"], ["texture"])}
    assert parse_announcement(b'{"gateway": "old", "ttl_ms": 5, "columns": {"RA": [0]}}')[1].decoders == {}
    for bad in (b"{", b"[]", b'{"gateway": 1, "ttl_ms": 5, "columns": {}}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {"XX": [0]}}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "channels": [-1]}',
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "decoders": {"a.b": [0]}}',  # not a subject token
                b'{"gateway": "g", "ttl_ms": 5, "columns": {}, "decoders": {"force": 0}}'):
        with pytest.raises(ValueError, match="malformed demand"):
            parse_announcement(bad)


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
    from touchreal.bridge.demand import MAX_ANNOUNCEMENT_BYTES, Rejected

    def reason(data: bytes, n_taxels: int = 4) -> str:
        with pytest.raises(Rejected) as exc:
            parse_announcement(data, n_taxels)
        return exc.value.reason

    assert reason(b" " * (MAX_ANNOUNCEMENT_BYTES + 1)) == "oversized"
    assert reason(announcement("g", Announced({"SA1": [4]}))) == "out_of_range"
    assert reason(announcement("g", Announced({}, [0], {"force": [9]}))) == "out_of_range"
    assert reason(announcement("g", Announced({"SA1": [0]}), ttl_s=61.0)) == "malformed"
    assert reason(announcement("a.b", Announced({"SA1": [0]}))) == "malformed"
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
