"""touchreal_client's sans-I/O parts: sequence-gap counting, latency from the frame clocks, backoff."""

from __future__ import annotations

import pytest
from touchreal_client import protocol as P
from touchreal_client.backoff import Backoff
from touchreal_client.errors import ParamsRejected
from touchreal_client.stats import LatencyEstimator, StreamStats
from touchreal_client.stream import stream_url


def _h(seq: int, dropped: int = 0, flags: int = 0, emit: int = 0, sent: int = 0) -> P.Header:
    return P.Header(P.KIND_SPIKES, seq=seq, dropped=dropped, flags=flags, emit_us=emit, sent_us=sent)


def test_seq_gaps_are_counted_per_connection_and_across_the_u32_wrap():
    st = StreamStats()
    st.on_connect(new_session=True)
    assert [st.on_frame(_h(s)) for s in (0, 1, 2, 5, 6)] == [0, 0, 0, 2, 0]
    st.on_frame(_h(9, dropped=4, flags=P.FLAG_SOURCE_GAP | P.FLAG_RESTARTED))
    assert (st.gaps, st.missed_frames, st.server_dropped, st.source_gaps, st.restarts) == (2, 4, 4, 1, 1)
    st.on_connect(new_session=False)  # a reconnect to the same session: seq starts again at 0, no gap
    assert st.on_frame(_h(0)) == 0 and st.reconnects == 1 and st.session_changes == 0
    st.on_connect(new_session=True)
    st.on_frame(_h(2**32 - 1))
    assert st.on_frame(_h(0)) == 0 and st.on_frame(_h(3)) == 2
    assert st.session_changes == 1 and st.frames == 10 and st.missed_frames == 6


def test_latency_uses_the_best_time_exchange_and_adds_the_algorithmic_latency():
    lat = LatencyEstimator()
    lat.set_algorithmic({"SA1": 148_000, "PC": 20_000})
    lat.add_time_sample(1_000, 6_000, 6_100, 3_000)  # delay 1900, offset 4050
    lat.add_time_sample(10_000, 14_100, 14_200, 10_400)  # delay 300 -> wins: offset 3950
    lat.add_time_sample(20_000, 30_000, 30_100, 29_000)  # delay 8900: ignored
    assert lat.offset_us == 3950 and lat.uncertainty_us == 150
    got = lat.on_frame(_h(0, emit=100_000, sent=101_000), recv_us=100_050)  # server time 104_000
    assert (got.queue_us, got.network_us, got.delivery_us) == (1_000, 3_000, 4_000)
    assert got.total_us == {"SA1": 152_000, "PC": 24_000}
    s = lat.summary()
    assert s.frames == 1 and s.delivery_median_us == 4_000 and s.total_median_us["PC"] == 24_000


def test_backoff_grows_with_full_jitter_caps_and_gives_up():
    b = Backoff(initial_s=0.1, factor=2, max_s=0.5, max_attempts=6, seed=1)
    delays = [b.next_delay() for _ in range(6)]
    caps = [0.1, 0.2, 0.4, 0.5, 0.5, 0.5]
    assert all(0 <= d <= c for d, c in zip(delays, caps)) and b.exhausted
    b.reset()
    assert not b.exhausted and b.attempt == 0
    with pytest.raises(ValueError):
        Backoff(initial_s=0)


def test_stream_url_from_base_urls():
    assert stream_url("http://h:1") == "ws://h:1/v1/stream"
    assert stream_url("https://h/") == "wss://h/v1/stream"
    assert stream_url("ws://h:1/v1/stream") == "ws://h:1/v1/stream"
    assert stream_url("h:1") == "ws://h:1/v1/stream"


def test_params_rejected_lists_every_field():
    detail = [{"loc": ["body", "classes", "SA1", "tau_ms"], "msg": "Input should be greater than 0"},
              {"loc": ["body", "schema"], "msg": "Field required"}]
    err = ParamsRejected("PUT", "/v1/params", 422, detail)
    assert err.errors == [("classes.SA1.tau_ms", "Input should be greater than 0"), ("schema", "Field required")]
    assert "classes.SA1.tau_ms: Input should be greater than 0" in str(err) and "2 invalid field(s)" in str(err)
