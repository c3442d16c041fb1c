"""The wire codec (touchreal_client.protocol): round trips, stamping, malformed input."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from touchreal_client import protocol as P


def _header(kind=P.KIND_SPIKES):
    return P.Header(kind, update=7, emit_us=1_700_000_000_000_000, params_rev=3, flags=P.FLAG_SOURCE_GAP)


@given(st.lists(st.tuples(st.integers(0, 2**64 - 1), st.integers(0, 65535), st.integers(0, 2)), max_size=50))
@settings(max_examples=50, deadline=None)
def test_spikes_round_trip_keeps_64_bit_times(events):
    events.sort()
    t, tx, c = (np.array([e[i] for e in events], dt) for i, dt in ((0, np.uint64), (1, np.uint16), (2, np.uint8)))
    final = {"SA1": 2**40 + 5, "RA": None, "PC": 2**33}
    buf = P.encode_spikes(_header(), t, tx, c, final)
    f = P.decode_frame(buf)
    assert isinstance(f, P.SpikesFrame)
    assert f.t_us.tolist() == t.tolist() and f.taxel.tolist() == tx.tolist() and f.cls.tolist() == c.tolist()
    assert f.final_us == final
    assert f.header.update == 7 and f.header.params_rev == 3 and f.header.flag_names() == ["source_gap"]
    assert len(buf) == P.HEADER_LEN + P.SPIKES_HEAD.size + 12 * len(events)


def test_stamp_sets_only_the_per_connection_fields():
    buf = P.encode_spikes(_header(), np.array([5], np.uint64), np.array([1]), np.array([2]), {"PC": 9})
    out = P.stamp(buf, seq=41, dropped=2, sent_us=123456789)
    h = P.decode_frame(out).header
    assert (h.seq, h.dropped, h.sent_us) == (41, 2, 123456789)
    changed = [i for i, (a, b) in enumerate(zip(buf, out)) if a != b]
    assert all(P.OFF_SEQ <= i < P.OFF_SEQ + 8 or P.OFF_SENT <= i < P.OFF_SENT + 8 for i in changed)


def test_channels_and_decoded_round_trip():
    data = np.random.default_rng(0).normal(size=(5, 3, 4)).astype(np.float32)
    f = P.decode_frame(P.encode_channels(_header(P.KIND_CHANNELS), 2**33, 5000, [0, 4, 7], data))
    assert isinstance(f, P.ChannelsFrame) and f.t0_us == 2**33 and f.period_us == 5000
    assert f.taxels.tolist() == [0, 4, 7] and np.array_equal(f.data, data)
    vals = np.arange(12, dtype=np.float32).reshape(2, 3, 2)
    d = P.decode_frame(P.encode_decoded(_header(P.KIND_DECODED), 1, [0, 1, 2], [10, 20], vals))
    assert isinstance(d, P.DecodedFrame) and d.decoder == 1 and d.t_us.tolist() == [10, 20]
    assert np.array_equal(d.values, vals)


def test_json_encoding_round_trips_through_the_per_connection_prefix():
    frame = P.SpikesFrame(_header(), np.array([1, 2], np.uint64), np.array([0, 3], np.uint16), np.array([0, 2], np.uint8),
                          {"SA1": 10, "RA": None, "PC": 4})
    text = P.render_json(json.dumps(P.frame_json_body(frame)), 5, 1, 99)
    msg = json.loads(text)
    assert msg["class"] == ["SA1", "PC"] and msg["seq"] == 5 and msg["final_us"] == {"SA1": 10, "PC": 4}
    back = P.frame_from_json(msg)
    assert back.t_us.tolist() == [1, 2] and back.final_us == frame.final_us and back.header.dropped == 1


@pytest.mark.parametrize(
    "buf, fragment",
    [
        (b"", "shorter than"),
        (b"XX" + bytes(60), "bad magic"),
        (P.HEADER.pack(P.MAGIC, 9, 1, 0, 48, 0, 0, 0, 0, 0, 0, 0), "unsupported frame version"),
        (P.HEADER.pack(P.MAGIC, 1, 9, 0, 48, 0, 0, 0, 0, 0, 0, 0), "unknown frame kind"),
        (P.HEADER.pack(P.MAGIC, 1, 1, 0, 48, 0, 0, 0, 0, 0, 0, 0) + P.SPIKES_HEAD.pack(3, 1, 0, 0, 0), "truncated"),
        (P.HEADER.pack(P.MAGIC, 1, 2, 0, 48, 0, 0, 0, 0, 0, 0, 0) + b"\0" * 4, "truncated"),
    ],
)
def test_malformed_frames_raise_protocol_errors(buf, fragment):
    with pytest.raises(P.ProtocolError, match=fragment):
        P.decode_frame(buf)


def test_bare_subscribe_gets_everything_in_binary():
    s = P.parse_subscribe({"type": "subscribe"})
    assert s.taxels is None and s.classes is None and s.streams == ["spikes"] and s.encoding == "binary"
    assert P.parse_subscribe(s.to_json()) == s


@pytest.mark.parametrize(
    "msg, fragment",
    [
        ({"version": 3}, "not supported"),
        ({"classes": ["SA2"]}, "unknown classes"),
        ({"taxels": [-1]}, "taxel ids"),
        ({"taxels": "all"}, "taxel ids"),
        ({"encoding": "xml"}, "encoding"),
        ({"streams": ["video"]}, "unknown streams"),
        ({"channels": {"decimation": 0}}, "decimation"),
        ({"colour": 1}, "unknown subscribe fields"),
    ],
)
def test_bad_subscriptions_are_named(msg, fragment):
    with pytest.raises(P.ProtocolError, match=fragment):
        P.parse_subscribe({"type": "subscribe", **msg})


def test_client_messages_and_clock_offset():
    with pytest.raises(P.ProtocolError, match="not valid JSON"):
        P.parse_client_message("{")
    with pytest.raises(P.ProtocolError, match='"type"'):
        P.parse_client_message("[1]")
    with pytest.raises(P.ProtocolError) as err:
        P.parse_client_message(" " * (P.MAX_CLIENT_MESSAGE_BYTES + 1))
    assert err.value.code == "too_big"
    # client clock 1000 us behind the server, 200 us each way, 50 us in the server
    offset, delay = P.clock_offset(0, 1200, 1250, 450)
    assert offset == 1000 and delay == 400


# -- at the size of a large skin (16,384 taxels and more) ---------------------------------------------------
def _grid(n: int, pitch: float = 10.0) -> list[tuple[float, float]]:
    """A near-square row-major grid centred on (0, 0), written out independently of the codec."""
    cols = 1
    while cols * cols < n:
        cols += 1
    rows = -(-n // cols)
    return [((i % cols - (cols - 1) / 2) * pitch, (i // cols - (rows - 1) / 2) * pitch) for i in range(n)]


def test_a_large_grid_skin_is_described_by_its_layout_and_a_small_one_is_listed_too():
    from touchreal_client.schema import message_schema

    import jsonschema

    for n in (1, 7, P.HELLO_LISTED_TAXELS, P.HELLO_LISTED_TAXELS + 1, 16384, P.MAX_TAXELS):
        grid = _grid(n)
        skin = json.loads(json.dumps(P.hello_skin(np.array(grid))))
        assert skin["n_taxels"] == n and skin["layout"]["kind"] == "grid"
        assert (skin["taxels"] is None) == (n > P.HELLO_LISTED_TAXELS)
        assert len(json.dumps(skin, separators=(",", ":"))) < (200 if n > P.HELLO_LISTED_TAXELS else 40 * n + 200)
        back = P.hello_positions(skin)
        assert back.shape == (n, 2) and np.abs(back - np.array(grid)).max() <= P.GRID_TOLERANCE_MM
        hello_schema = message_schema("hello")["components"]["schemas"]["hello"]["properties"]
        for key in ("n_taxels", "layout", "taxels"):
            jsonschema.validate(skin[key], {**hello_schema[key], "components": message_schema("hello")["components"]})
    # centres that form no grid are listed, whatever their number
    ragged = np.array(_grid(5000))
    ragged[4321] += 0.5
    skin = P.hello_skin(ragged)
    assert skin["layout"] is None and len(skin["taxels"]) == 5000 and np.array_equal(P.hello_positions(skin), ragged)


@pytest.mark.parametrize(
    "hello, fragment",
    [
        ({"taxels": None}, "n_taxels and a grid layout"),
        ({"taxels": None, "n_taxels": 70000, "layout": {"kind": "grid"}}, "n_taxels and a grid layout"),
        ({"taxels": None, "n_taxels": 9, "layout": {"kind": "grid", "rows": 2, "cols": 4, "x0_mm": 0, "y0_mm": 0,
                                                     "dx_mm": 1, "dy_mm": 1}}, "covering n_taxels"),
        ({"taxels": None, "n_taxels": 4, "layout": {"kind": "grid", "rows": 2, "cols": 2, "x0_mm": 0, "y0_mm": 1e400,
                                                     "dx_mm": 1, "dy_mm": 1}}, "finite"),
        ({"taxels": [{"id": 1, "x_mm": 0, "y_mm": 0}]}, "ids 0..n-1"),
        ({"taxels": [{"id": 0, "x_mm": "0", "y_mm": 0}]}, "finite numbers"),
    ],
)
def test_a_malformed_skin_description_is_a_protocol_error(hello, fragment):
    with pytest.raises(P.ProtocolError, match=fragment):
        P.hello_positions(hello)


@given(st.lists(st.tuples(st.integers(0, 70), st.integers(0, 70)), max_size=6),
       st.lists(st.tuples(*[st.floats(-40, 40, allow_nan=False)] * 4), max_size=3),
       st.none() | st.lists(st.integers(0, 63), max_size=8))
@settings(max_examples=60, deadline=None)
def test_a_region_names_exactly_the_taxels_in_its_ranges_and_rectangles(ranges, rects, ids):
    ranges = [[min(a, b), max(a, b)] for a, b in ranges]
    rects = [{"x_mm": sorted(r[:2]), "y_mm": sorted(r[2:])} for r in rects]
    sub = P.parse_subscribe({"type": "subscribe", "taxels": ids, "region": {"ranges": ranges, "rects": rects}})
    assert P.parse_subscribe(json.loads(json.dumps(sub.to_json()))) == sub
    grid = _grid(64)
    want = set(ids or ())  # brute force, one taxel at a time
    want |= {t for a, b in ranges for t in range(a, min(b, 64))}
    want |= {t for t, (x, y) in enumerate(grid) for r in rects
             if r["x_mm"][0] <= x <= r["x_mm"][1] and r["y_mm"][0] <= y <= r["y_mm"][1]}
    assert sub.taxel_ids(64, np.array(grid)).tolist() == sorted(want)
    assert P.Subscription().taxel_ids(64) is None  # no taxels, no region: every taxel


def test_a_region_subscription_of_the_whole_skin_is_small_and_a_list_of_ids_is_not():
    region = P.Subscription(region=P.Region(ranges=((0, 16384),), rects=((-640.0, 640.0, -640.0, 0.0),)))
    assert len(json.dumps(region.to_json())) < 300
    assert "region" not in P.Subscription(taxels=[1]).to_json()  # a server older than regions sees no new field
    with pytest.raises(P.ProtocolError) as err:
        P.parse_client_message(json.dumps({"type": "subscribe", "taxels": list(range(16384))}))
    assert err.value.code == "too_big"


@pytest.mark.parametrize(
    "region, fragment",
    [
        ("all", "region must be"),
        ({"ranges": [[0, 1]], "shape": "circle"}, "region must be"),
        ({"ranges": [[5, 2]]}, "0 <= start <= stop"),
        ({"ranges": [[0, P.MAX_TAXELS + 1]]}, "0 <= start <= stop"),
        ({"ranges": [[0, True]]}, "0 <= start <= stop"),
        ({"ranges": [[0.0, 3]]}, "0 <= start <= stop"),
        ({"ranges": [[i, i + 1] for i in range(P.MAX_REGION_RANGES + 1)]}, "at most"),
        ({"rects": [{"x_mm": [0, 1]}]}, "rectangles"),
        ({"rects": [{"x_mm": [1, 0], "y_mm": [0, 1]}]}, "min <= max"),
        ({"rects": [{"x_mm": [0, float("inf")], "y_mm": [0, 1]}]}, "finite"),
        ({"rects": [{"x_mm": [0, 10**400], "y_mm": [0, 1]}]}, "finite"),
        ({"rects": [{"x_mm": [0, 1], "y_mm": [0, 1]}] * (P.MAX_REGION_RECTS + 1)}, "at most"),
    ],
)
def test_bad_regions_are_named(region, fragment):
    with pytest.raises(P.ProtocolError, match=fragment) as err:
        P.parse_subscribe({"type": "subscribe", "region": region})
    assert err.value.code == "bad_message"


def test_the_busiest_spikes_frame_of_16384_taxels_round_trips_binary_and_json():
    """Every taxel, every class, as many spikes as the refractory period allows (one per 1.2 ms): 5 per
    5 ms hop for SA1 and RA, 27 per 32 ms PC update; 37 events a taxel, 444 bytes."""
    import struct

    n, per_class = 16384, (5, 5, 27)
    base = 2**42  # sensor stamps of 13 digits
    t = np.concatenate([np.repeat(base + np.arange(m, dtype=np.uint64) * 1200, n) for m in per_class])
    tx = np.concatenate([np.tile(np.arange(n), m) for m in per_class]).astype(np.uint16)
    c = np.concatenate([np.full(m * n, k) for k, m in enumerate(per_class)]).astype(np.uint8)
    order = np.argsort(t, kind="stable")
    t, tx, c = t[order], tx[order], c[order]
    header = P.Header(P.KIND_SPIKES, update=2**40, emit_us=1_763_900_000_123_456, params_rev=2**32 - 1, flags=7,
                      seq=2**32 - 1, dropped=2**32 - 1, sent_us=1_763_900_000_123_999)
    final = {"SA1": base + 6000, "RA": base + 6000, "PC": base + 32000}
    buf = P.encode_spikes(header, t, tx, c, final)
    assert len(buf) == 80 + 12 * 37 * n == 7_274_576  # the largest frame of a 16,384-taxel skin (docs)
    # read back without the codec: the documented offsets and event layout
    assert buf[:4] == b"TR\x01\x01" and struct.unpack_from("<HIIQ", buf, 6)[1:] == (2**32 - 1, 2**32 - 1, 2**40)
    assert struct.unpack_from("<IB", buf, 48) == (37 * n, 0b111)
    ev = np.frombuffer(buf, np.dtype([("t", "<u8"), ("id", "<u2"), ("k", "u1"), ("pad", "u1")]), offset=80)
    assert np.array_equal(ev["t"], t) and np.array_equal(ev["id"], tx) and np.array_equal(ev["k"], c)
    f = P.decode_frame(buf)
    assert f.t_us.size == 37 * n and np.array_equal(f.taxel, tx) and f.final_us == final
    text = P.render_json(json.dumps(P.frame_json_body(f), separators=(",", ":")), 5, 0, 7)
    assert len(text) < 26 * 37 * n  # about 25 bytes an event with 13-digit stamps (docs)
    back = P.frame_from_json(json.loads(text))
    assert np.array_equal(back.t_us, t) and np.array_equal(back.taxel, tx) and np.array_equal(back.cls, c)
