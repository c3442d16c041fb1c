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
        ({"version": 2}, "not supported"),
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
