"""Real time, or honest about it: a skin and subscription larger than the machine can serve sheds
load explicitly (seq gaps, restarted + source_gap frames, metrics, status, health) and its spikes
stay within the lag bound of their causing samples; a skin it can serve does not shed."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import pytest
from server_harness import connect, hello_and_subscribe, memory_mib, running_server, wait_until
from touchreal_client import protocol as P
from touchreal_client.clock import ClockMap, ClockPoint

from touchreal.server.settings import RuntimeConfig

MAX_LAG_MS = 250.0
DELIVERY_MS = 150.0  #: the hub and loopback, allowed generously for a loaded CI machine


async def _watch(addr: str, done, deadline_s: float) -> dict:
    """Receive everything until ``done(state)`` holds (AssertionError at ``deadline_s``): frames, the
    clock model, seq gaps and, per SA1 spike, the client's latency from its causing sample (arrival
    on the server's wall clock minus the sample's acquisition by the clock model; loopback, one clock)."""
    state = {"gaps": 0, "dropped": 0, "flags": 0, "restarted_gap": 0, "sa1_latency_ms": [], "frames": 0, "max_taxel": -1}
    clocks = ClockMap()
    async with connect(addr, max_size=None) as ws:
        hello, _ = await hello_and_subscribe(ws)
        if hello.get("clock"):
            clocks.update(ClockPoint.from_json({"type": "clock", **hello["clock"]}))
        last_seq, end = None, time.monotonic() + deadline_s
        while not done(state):
            assert time.monotonic() < end, f"not within {deadline_s} s: {({k: v for k, v in state.items() if k != 'sa1_latency_ms'})}"
            msg = await asyncio.wait_for(ws.recv(), max(0.1, end - time.monotonic()))
            arrived_us = time.time_ns() // 1000
            if isinstance(msg, str):
                m = json.loads(msg)
                if m["type"] == "clock":
                    clocks.update(ClockPoint.from_json(m))
                continue
            f = P.decode_frame(msg)
            state["frames"] += 1
            if last_seq is not None and f.header.seq > last_seq + 1:
                state["gaps"] += 1
                state["dropped"] = f.header.dropped
                if f.header.flags & P.FLAG_RESTARTED and f.header.flags & P.FLAG_SOURCE_GAP:
                    state["restarted_gap"] += 1
            last_seq = f.header.seq
            if isinstance(f, P.SpikesFrame) and f.taxel.size:
                state["max_taxel"] = max(state["max_taxel"], int(f.taxel.max()))
            if isinstance(f, P.SpikesFrame) and clocks.last is not None:
                sa1 = f.t_us[f.cls == 0].astype(np.float64) - hello["delay_us"]["SA1"]
                if sa1.size:
                    state["sa1_latency_ms"] += list((arrived_us - clocks.to_server_wall_us(sa1)) / 1e3)
    return state


def _get(addr: str, path: str):
    r = httpx.get(f"http://{addr}{path}", timeout=10)
    return r.json() if path != "/metrics" else r.text


def test_a_skin_too_large_for_the_machine_sheds_load_and_says_so(tmp_path):
    # 4096 taxels, dense, everything subscribed: about 2.5x the compute real time allows on 2 cores (the
    # simulated skin itself keeps up; a source that falls behind is shed as well, but sends nothing).
    # 2048 dense came within reach of real time on a 2-core AMD EPYC VM (no shed in 240 s)
    with running_server(tmp_path, RuntimeConfig(taxels=4096), dense=True, max_lag_ms=MAX_LAG_MS) as (addr, svc):
        wait_until(lambda: svc.runtime is not None and svc.runtime.state != "starting", 120, "the runtime started")
        state = asyncio.run(_watch(addr, lambda s: s["restarted_gap"] >= 1 and len(s["sa1_latency_ms"]) >= 1, 240))
        st = _get(addr, "/v1/status")["realtime"]
        health = _get(addr, "/v1/health")
        metrics = _get(addr, "/metrics")
    assert state["dropped"] >= 1  # the loss is a seq gap every client sees, flagged restarted + source_gap
    assert st["compute"] == "dense" and st["sheds"] >= 1 and st["shed_ms"] > 0  # (the real-time factor restarts low
    # after each shed: its value at any one moment says nothing here)
    assert health["status"] == "degraded" and "fell behind" in health["reason"]
    shed = float(next(line.split()[1] for line in metrics.splitlines() if line.startswith("touchreal_shed_seconds_total")))
    assert shed > 0
    assert 'touchreal_dropped_frames_total{reason="upstream_loss"}' in metrics
    # the spikes that do go out are bounded in time: the server checks the lag bound after each phase's
    # compute, so only SA1's look-ahead (20 ms) and the delivery to this client (hub, loopback) add to it
    lat = np.array(state["sa1_latency_ms"])
    assert lat.max() < MAX_LAG_MS + 20 + DELIVERY_MS, np.percentile(lat, [50, 99, 100])


@pytest.mark.slow
def test_a_skin_the_machine_serves_streams_without_shedding(tmp_path):
    with running_server(tmp_path, RuntimeConfig(taxels=4)) as (addr, svc):
        wait_until(lambda: svc.runtime is not None and svc.runtime.state != "starting", 120, "the runtime started")
        state = asyncio.run(_watch(addr, lambda s: len(s["sa1_latency_ms"]) >= 5, 60))
        st = _get(addr, "/v1/status")["realtime"]
    assert state["gaps"] == 0 and st["sheds"] == 0 and st["compute"] == "dense"  # 4 taxels: one block
    assert 0 < st["real_time_factor"] < 1 and st["lag_ms"] < MAX_LAG_MS
    assert np.median(state["sa1_latency_ms"]) < 100


@pytest.mark.slow  # 65,536 taxels: one to two minutes
def test_the_largest_skin_the_service_accepts_streams_end_to_end(tmp_path):
    """65,536 taxels (the protocol's largest: ids are uint16), the large scene at 1 % touched, one client
    subscribed to everything: the service starts, says hello, and streams spikes from across the id
    range within the lag bound, shedding or not (honest about it either way), running only the taxels a
    contact keeps awake once the detector has judged them, in less than 4 GiB more memory. (On the
    2-core AMD EPYC VM it sheds and its skin falls behind a few times a minute, health degraded with
    the reason; SA1 ~190 ms after its causing sample; 0.8 GiB more at its peak.)"""
    rss0 = memory_mib()
    with running_server(tmp_path, RuntimeConfig(taxels=P.MAX_TAXELS), sim_touched=0.01, max_lag_ms=MAX_LAG_MS) as (addr, svc):
        wait_until(lambda: svc.runtime is not None and svc.runtime.state != "starting", 300, "the runtime started")
        state = asyncio.run(_watch(addr, lambda s: len(s["sa1_latency_ms"]) >= 500 and s["max_taxel"] >= 49152, 300))
        st = _get(addr, "/v1/status")["realtime"]
        health = _get(addr, "/v1/health")
    assert st["taxels"] == P.MAX_TAXELS and st["compute"] == "sparse" and 0 < st["awake_taxels"] < P.MAX_TAXELS // 8
    assert st["sheds"] >= (state["restarted_gap"] > 0)  # a restarted gap the client saw is a shed the service counted
    assert health["status"] == "ok" or (health["status"] == "degraded" and health["reason"]), health
    lat = np.array(state["sa1_latency_ms"])
    assert lat.max() < MAX_LAG_MS + 20 + DELIVERY_MS, np.percentile(lat, [50, 99, 100])
    assert memory_mib("VmHWM") - rss0 < 4 * 1024
