"""``touchreal bridge lsl``: a real service on loopback, the bridge's LSL outlets (pylsl, bundled
liblsl) and pylsl inlets on this machine; the spikes and channels are compared with a direct
``/v1/stream`` client of the same service and the timestamps with its clock model."""

from __future__ import annotations

import asyncio
import uuid
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from server_harness import bridge_running, running_server, until
from touchreal_client import AsyncStream, Subscription
from touchreal_client import protocol as P

pylsl = pytest.importorskip("pylsl", reason="pylsl is not installed (pip install -e 'clients/python[lsl]')")
from touchreal_client.bridges.lsl import LslBridge, lsl_minus_wall_s  # noqa: E402

TOLERANCE_S = 0.002


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


async def _inlet(source_id: str):
    infos = await asyncio.to_thread(pylsl.resolve_byprop, "source_id", source_id, 1, 10.0)
    if not infos:
        pytest.skip(f"liblsl cannot resolve its own outlet {source_id!r} on this machine (no multicast/loopback discovery)")
    inlet = pylsl.StreamInlet(infos[0], max_buflen=60, recover=False)
    await asyncio.to_thread(inlet.open_stream, 10.0)
    info = await asyncio.to_thread(inlet.info, 10.0)
    return inlet, info


def _pull(inlet, samples: list, stamps: list) -> None:
    data, ts = inlet.pull_chunk(timeout=0.0, max_samples=100000)
    samples.extend(data)
    stamps.extend(ts)


def test_every_spike_and_channel_sample_reaches_an_lsl_inlet_at_its_mapped_time(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        url = f"ws://{addr}/v1/stream"

        async def go():
            bridge = LslBridge(url, name=f"TouchReal-test-{uuid.uuid4().hex[:8]}")
            async with bridge_running(bridge):
                async with AsyncStream(url, Subscription(streams=["spikes", "channels"])) as direct:
                    s_inlet, s_info = await _inlet(bridge.source_ids["spikes"])
                    c_inlet, c_info = await _inlet(bridge.source_ids["channels"])
                    lsl_spikes: list = []
                    lsl_spike_ts: list = []
                    lsl_chans: list = []
                    lsl_chan_ts: list = []
                    frames: list = []
                    async for f in direct.frames():
                        frames.append(f)
                        _pull(s_inlet, lsl_spikes, lsl_spike_ts)
                        _pull(c_inlet, lsl_chans, lsl_chan_ts)
                        if len(frames) >= 120 and sum(x.t_us.size for x in frames if isinstance(x, P.SpikesFrame)) >= 100:
                            break
                    # one machine, one wall clock: the server's wall time of a stamp is the local one
                    offset, wall = lsl_minus_wall_s(), direct.clock.to_server_wall_us
                    # + the stated sync errors of both clocks that map the stamps: the bridge's and the direct client's
                    tolerance = TOLERANCE_S + (bridge.stream.clock.offset_error_us + (direct.clock.offset_error_us or 0.0)) / 1e6
                    spikes = [(int(t), int(x), int(c), wall(int(t)) / 1e6 + offset)
                              for f in frames if isinstance(f, P.SpikesFrame) for t, x, c in zip(f.t_us, f.taxel, f.cls)]
                    chans = [(wall(int(f.t0_us + k * f.period_us)) / 1e6 + offset, f.taxels, f.data[k])
                             for f in frames if isinstance(f, P.ChannelsFrame) for k in range(f.data.shape[0])]
                    def pushed() -> bool:  # the bridge has pushed what the direct client has seen
                        _pull(s_inlet, lsl_spikes, lsl_spike_ts)
                        _pull(c_inlet, lsl_chans, lsl_chan_ts)
                        return bool(lsl_spike_ts) and lsl_spike_ts[-1] >= spikes[-1][3] - TOLERANCE_S

                    await until(pushed, 30, "the inlet got the direct client's last spike")
                    return (spikes, chans, lsl_spikes, lsl_spike_ts, lsl_chans, lsl_chan_ts,
                            s_info.as_xml(), c_info.as_xml(), svc.view.n_taxels, tolerance)

        spikes, chans, lsl_spikes, lsl_ts, lsl_chans, lsl_chan_ts, s_xml, c_xml, n_taxels, tolerance = run(go())

    # spikes: the inlet's samples are the direct stream's spikes, in order, none missing, each at its mapped time
    assert len(lsl_spikes) >= 50, f"only {len(lsl_spikes)} spikes reached the inlet"
    start = next((j for j, (_, x, c, m) in enumerate(spikes)
                  if [x, c] == list(lsl_spikes[0]) and abs(m - lsl_ts[0]) < tolerance), None)
    assert start is not None, "the inlet's first spike is not among the direct stream's spikes"
    n = min(len(lsl_spikes), len(spikes) - start)
    assert n >= 50
    assert [list(s) for s in lsl_spikes[:n]] == [[x, c] for _, x, c, _ in spikes[start:start + n]]
    err = np.abs(np.array(lsl_ts[:n]) - np.array([m for *_, m in spikes[start:start + n]]))
    assert err.max() < tolerance, err.max()

    # channels: each inlet sample is the direct stream's sample at its mapped time, same values
    mapped = np.array([m for m, _, _ in chans])
    seen = [(ts, v) for ts, v in zip(lsl_chan_ts, lsl_chans) if ts <= mapped[-1] + tolerance]
    assert len(seen) >= 100, f"only {len(seen)} channel samples reached the inlet"
    for ts, values in seen:
        k = int(np.argmin(np.abs(mapped - ts)))
        assert abs(mapped[k] - ts) < tolerance, f"an inlet sample at {ts} matches no direct sample"
        _, taxels, data = chans[k]
        got = np.asarray(values, np.float32).reshape(n_taxels, len(P.CHANNELS))[taxels.astype(int)]
        np.testing.assert_array_equal(got, data)
    # 200 Hz, none missing or repeated: a lost sample is a 10 ms step, a repeated one a 0 ms step; steps
    # off 5 ms by up to the mapping tolerance are the bridge re-estimating its clock offset under load,
    # which the per-sample check above already bounds
    steps = np.diff([ts for ts, _ in seen])
    odd = steps[np.abs(steps - 0.005) >= 0.0025]
    assert odd.size == 0, f"steps of 7.5 ms or more (a lost sample) or 2.5 ms or less (a repeat): {odd}"

    # metadata in the StreamInfo XML
    s_root, c_root = ET.fromstring(s_xml), ET.fromstring(c_xml)
    assert s_root.findtext("nominal_srate").startswith("0") and s_root.findtext("channel_format") == "int32"
    assert [c.findtext("name") for c in s_root.iter("class")] == list(P.CLASSES)
    assert len(list(s_root.iter("taxel"))) == n_taxels
    assert float(c_root.findtext("nominal_srate")) == 200.0
    labels = [(c.findtext("label"), c.findtext("unit")) for c in c_root.find("desc/channels")]
    assert labels[:4] == [("0.ST", "N"), ("0.dST", "N/s"), ("0.PVDF", "V"), ("0.dPVDF", "V/s")]
    assert len(labels) == 4 * n_taxels


def test_a_population_reaches_lsl_as_afferent_spikes_described_in_the_stream_info(tmp_path):
    import json

    from touchreal.server.settings import RuntimeConfig

    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"variants": {"SA1": [1.0], "RA": [1.0], "PC": [1.0]}}))
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(plan)) as (addr, svc):

        async def go():
            bridge = LslBridge(f"ws://{addr}/v1/stream", name=f"TouchReal-test-{uuid.uuid4().hex[:8]}")
            async with bridge_running(bridge):
                inlet, info = await _inlet(bridge.source_ids["spikes"])
                samples: list = []

                def enough() -> bool:
                    _pull(inlet, samples, [])
                    return len(samples) >= 30

                await until(enough, 60, "30 afferent spikes at the inlet")
                return set(bridge.source_ids), info.as_xml(), samples

        ids, xml, samples = run(go())
        pop = svc.population
    assert ids == {"spikes"}  # a population has no channels stream
    listed = ET.fromstring(xml).find("desc/afferents")
    assert listed is not None and len(listed) == len(pop) == 940
    first = listed[0]
    assert first.findtext("id") == "0" and first.findtext("class") == "SA1"
    assert float(first.findtext("x_mm")) == pytest.approx(pop.layout.xy_mm[0, 0], abs=1e-3)  # the hello rounds to um
    assert ET.fromstring(xml).find("desc/channels")[0].findtext("label") == "afferent"
    ids_cls = np.array(samples, np.int64)
    assert (ids_cls[:, 0] < len(pop)).all() and np.array_equal(pop.layout.cls[ids_cls[:, 0]], ids_cls[:, 1])
