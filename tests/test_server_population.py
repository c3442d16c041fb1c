"""`serve --population`: a real server whose spikes address afferents (protocol version 2)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
import websockets
from server_harness import collect, connect, hello_and_subscribe, n_spikes, running_server
from touchreal_client import protocol as P

from touchreal.population.encoder import Population
from touchreal.population.layout import PopulationPlan
from touchreal.server.settings import RuntimeConfig

PLAN = {"seed": 4, "variants": {"SA1": [0.8, 1.2], "RA": [1.0], "PC": [0.9, 1.1]}}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 90))


async def _reply(ws) -> dict:
    while (msg := json.loads(await ws.recv()))["type"] == "clock":
        pass
    return msg


@pytest.fixture
def plan_file(tmp_path):
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(PLAN))
    return path


def test_population_hello_subscriptions_by_class_and_region_and_refusals(tmp_path, plan_file):
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(plan_file)) as (addr, svc):

        async def scenario():
            out = {}
            async with connect(addr) as ws:  # a version-1 subscriber would read afferents as taxels
                await ws.recv()
                await ws.send(json.dumps({"type": "subscribe", "version": 1}))
                out["v1"] = await _reply(ws)
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:
                        await asyncio.wait_for(ws.recv(), 5)
                out["v1_close"] = closed.value.rcvd.code
            async with connect(addr) as ws:
                await ws.recv()
                await ws.send(json.dumps({"type": "subscribe", "version": 2, "streams": ["spikes", "channels"]}))
                out["channels"] = await _reply(ws)
            async with connect(addr) as ws:
                hello, sub = await hello_and_subscribe(ws, version=2, classes=["SA1", "RA"],
                                                       region={"rects": [{"x_mm": [-100.0, 0.0], "y_mm": [-100.0, 100.0]}]})
                out["hello"], out["sub"] = hello, sub
                out["frames"] = await collect(ws, 60, until=lambda f: n_spikes(f) >= 30, what="30 spikes of the left half")
                out["active"] = {c: set(xs) for c, xs in svc.runtime.encoder.active.items()}
            return out

        out = run(scenario())
        pop = svc.population
    assert out["v1"]["code"] == "unsupported_version" and "afferents" in out["v1"]["message"]
    assert out["v1_close"] == P.CLOSE_UNSUPPORTED_VERSION
    assert out["channels"]["code"] == "not_served" and "per taxel" in out["channels"]["message"]
    hello = out["hello"]
    assert hello["version"] == 2 and hello["addresses"] == "afferents" and hello["n_taxels"] == 4
    assert hello["streams"]["decoded"]["decoders"] == []  # decoders read taxels: none offered to a population
    aff = P.hello_afferents(hello)
    # the plan from the file, placed over the 4 taxels' cells (10 mm pitch: 4 cm^2) at the fingertip densities
    expected = Population.build(np.asarray([[t["x_mm"], t["y_mm"]] for t in hello["taxels"]]), PopulationPlan.from_dict(PLAN))
    assert len(aff.cls) == len(expected) == 280 + 560 + 100
    assert np.array_equal(aff.cls, expected.layout.cls) and np.array_equal(aff.model, expected.layout.model)
    assert np.allclose(aff.xy_mm, expected.layout.xy_mm, atol=1e-3)
    assert aff.plan["seed"] == 4 and aff.plan["cell_mm"] == pytest.approx(10.0)
    spikes = [f for f in out["frames"] if isinstance(f, P.SpikesFrame)]
    ids = np.concatenate([f.taxel for f in spikes]).astype(np.int64)
    cls = np.concatenate([f.cls for f in spikes])
    assert (aff.xy_mm[ids, 0] <= 0.0).all()  # the region's afferents only
    assert np.array_equal(aff.cls[ids], cls) and set(cls.tolist()) <= {0, 1}  # the spike's class is its afferent's
    # compute follows demand per afferent: only the subscribed afferents' columns run
    active = out["active"]
    left = set(np.flatnonzero(aff.xy_mm[:, 0] <= 0.0).tolist())
    assert active.keys() <= {"SA1", "RA"}
    assert active["SA1"] | active.get("RA", set()) <= left and active["SA1"] == left & set(aff.ids("SA1").tolist())
    assert pop is not None and len(pop) == len(aff.cls)


def test_a_bad_population_plan_is_a_clear_source_error(tmp_path):
    bad = tmp_path / "plan.json"
    bad.write_text(json.dumps({"density_per_cm2": {"Merkel": 3}}))
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(bad)) as (addr, svc):
        assert svc.runtime is None and "Merkel" in (svc.source_error or "")


@pytest.mark.slow
def test_a_population_recording_exports_one_nwb_unit_per_afferent(tmp_path, plan_file):
    from pynwb import NWBHDF5IO
    from test_export_nwb import _inspect
    from touchreal_client.session import read_mcap

    from touchreal.cli import main

    rec, out = tmp_path / "pop.mcap", tmp_path / "pop.nwb"
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(plan_file)) as (addr, svc):
        # record asks for every stream; a population serves spikes only, and record says so in its subscription
        assert main(["record", f"http://{addr}", "--out", str(rec), "--seconds", "3"]) == 0
    s = read_mcap(rec)
    aff = s.afferents
    assert aff is not None and len(aff.cls) == 940 and s.t_us.size > 0 and s.channels is None
    assert main(["export", "nwb", str(rec), "--out", str(out)]) == 0
    assert _inspect(out) == []
    origin = s.origin_us()
    with NWBHDF5IO(str(out), "r") as io:
        df = io.read().units.to_dataframe()
    assert len(df) == len(aff.cls) and list(df.afferent) == list(range(len(aff.cls)))
    for r in df.itertuples():
        a = int(r.afferent)
        assert r.afferent_class == P.CLASSES[aff.cls[a]] and r.model == aff.model[a]
        assert np.allclose(r.position_mm, aff.xy_mm[a])
        want = np.sort(s.t_us[s.taxel == a])
        assert np.array_equal(np.round(np.asarray(r.spike_times) * 1e6).astype(np.int64) + origin, want)
    assert sum(len(r.spike_times) for r in df.itertuples()) == s.t_us.size


def test_bridges_ask_a_population_for_spikes_only():
    """A Foxglove or ROS 2 viewer of a channel topic must not get the spike topics refused along with it."""
    from touchreal_client.topics import CHANNELS_TOPIC, spikes_topic, wanted_subscription

    hello = {"addresses": "afferents", "population": {"n_afferents": 2, "classes": {"SA1": [[0, 1]], "RA": [[1, 2]]},
                                                      "x_mm": [0.0, 1.0], "y_mm": [0.0, 0.0], "model": [0, 0], "plan": {}}}
    topics = [spikes_topic("SA1"), CHANNELS_TOPIC]
    assert wanted_subscription(topics).streams == ["spikes", "channels"]
    sub = wanted_subscription(topics, hello=hello)
    assert sub.streams == ["spikes"] and sub.classes == ["SA1"]
    assert wanted_subscription([CHANNELS_TOPIC], hello=hello).streams == []
