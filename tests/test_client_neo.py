"""touchreal_client.neo: spikes received from a real server (frames, and a recording) as neo SpikeTrains,
analysed with elephant."""

from __future__ import annotations

import time

import numpy as np
import pytest
import quantities as pq
from elephant.statistics import mean_firing_rate, time_histogram
from server_harness import covers, running_server
from touchreal_client import Client, SpikesFrame, Subscription
from touchreal_client import protocol as P
from touchreal_client.neo import spiketrains
from touchreal_client.session import read_mcap

from touchreal.cli import main
from touchreal.server.settings import RuntimeConfig


def test_spike_frames_and_a_recording_become_neo_spiketrains(tmp_path):
    with running_server(tmp_path / "state", RuntimeConfig(taxels=2)) as (addr, svc):
        with Client(f"http://{addr}") as tr, tr.stream(Subscription(classes=["SA1", "PC"])) as s:
            # 2 s of the stream (the trains' duration is checked below), spikes among it; 60 s bound a failure
            frames, cover, end = [], covers(2.0), time.monotonic() + 60
            for f in s.frames():
                frames.append(f)
                if cover(frames) and sum(x.t_us.size for x in frames if isinstance(x, SpikesFrame)) > 0:
                    break
                assert time.monotonic() < end, "not within 60 s: 2 s of the stream, with spikes"
            hello = s.hello
        assert main(["record", f"http://{addr}", "--out", str(tmp_path / "r.mcap"), "--seconds", "1.5",
                     "--streams", "spikes"]) == 0
    trains = spiketrains(frames, hello=hello)
    assert [(st.annotations["taxel"], st.annotations["afferent_class"]) for st in trains] == \
        [(0, "SA1"), (0, "PC"), (1, "SA1"), (1, "PC")]
    spikes = [f for f in frames if isinstance(f, SpikesFrame)]
    t = np.concatenate([f.t_us for f in spikes]).astype(np.int64)
    taxel = np.concatenate([f.taxel for f in spikes])
    cls = np.concatenate([f.cls for f in spikes])
    for st in trains:
        k, tx = P.CLASSES.index(st.annotations["afferent_class"]), st.annotations["taxel"]
        want = np.sort(t[(cls == k) & (taxel == tx)])
        assert np.array_equal(np.round(st.times.rescale(pq.us).magnitude).astype(np.int64), want)
        # t_stop: the latest finality of the class (a pipeline that shed load and restarted reports less for a while)
        c = st.annotations["afferent_class"]
        assert round(float(st.t_stop.rescale(pq.us).magnitude)) == max(v for f in spikes if (v := f.final_us.get(c)) is not None)
        assert st.annotations["x_mm"] == hello["taxels"][tx]["x_mm"]
        duration = (st.t_stop - st.t_start).rescale(pq.s).magnitude
        assert 1.5 < duration < 10
        rate = mean_firing_rate(st).rescale(pq.Hz).magnitude
        assert rate == pytest.approx(want.size / duration, rel=1e-12)
    hist = time_histogram(trains, bin_size=100 * pq.ms, t_start=max(st.t_start for st in trains),
                          t_stop=min(st.t_stop for st in trains))
    assert hist.magnitude.sum() > 0

    rec = spiketrains(read_mcap(tmp_path / "r.mcap"))
    assert len(rec) == 6 and sum(st.size for st in rec) > 0  # the recorder took every class
    assert all(st.t_stop - st.t_start > 1.0 * pq.s for st in rec)
