"""Service benchmark: latency and fan-out of the running server (the paper's Table 4), and the saving
from computing only what subscribers need.

Part 1 starts the service on the simulated e-skin (uvicorn on 127.0.0.1, this process) and one
WebSocket client in another process. Per class it reports the end-to-end latency of every spike
from the acquisition of the sample that caused it (stamp minus the class delay, mapped to the wall
time its chunk was read) to its frame leaving the server (``sent_us``) and to the client's receipt,
plus the update interval, windows and mean compute overhead per update.

Part 2 connects 1, 10 and 100 subscribers (client processes) and reports events/s received, the
fan-out latency (receipt minus ``emit_us``) p50/p99 and frames dropped. ``--soak-seconds`` runs the
last count for that long.

With ``--nats`` (needs Debian's ``nats-server``), part 2 runs again through NATS: the service
publishes (``--publish``), two ``touchreal gateway`` processes serve the subscribers (spread evenly
over both), all on loopback; the latency is the same receipt minus ``emit_us`` (the publisher's
encoder), so the broker hop and the gateway are included; then one subscriber to the decoded force
takes each path in turn (the decoder runs in the service; its outputs cross on ``decoded.force``).

Part 3 drives the pipeline directly and compares the compute time per update for what a demand
needs: everything, one class, one taxel of many, a PVDF-free class, and nobody.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..params import EncoderParams, default_params
from ..settings import CLASSES

BENCH_SENSOR = "bench"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="length of each measurement (s)")
    p.add_argument("--subscribers", default=None, help="subscriber counts for the fan-out part (default 1,10,100; "
                   "with --nats the --nats-subscribers counts, so both paths are measured side by side)")
    p.add_argument("--soak-seconds", type=float, default=60.0, help="length of the largest fan-out run (s)")
    p.add_argument("--taxels", type=int, default=1, help="taxels of the simulated e-skin")
    p.add_argument("--params", type=Path, default=None, help="parameter file (default: shipped)")
    p.add_argument("--processes", type=int, default=2, help="client processes for the fan-out part")
    p.add_argument("--nats", action="store_true", help="also measure fan-out through NATS and two gateways")
    p.add_argument("--nats-subscribers", default="1,100,300", help="subscriber counts through the gateways")


# -- client side (runs in child processes) -------------------------------------------------------------
async def _one_client(addr: str, seconds: float, sub: dict) -> np.ndarray:
    """Rows (update, emit_us, sent_us, recv_us, n_events, seq, dropped) per spikes frame."""
    import websockets
    from touchreal_client import protocol as P

    rows = []
    async with websockets.connect(f"ws://{addr}/v1/stream", compression=None, max_size=None) as ws:
        await ws.recv()  # hello
        await ws.send(json.dumps({"type": "subscribe", **sub}))
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                msg = await asyncio.wait_for(ws.recv(), max(end - time.monotonic(), 0.001))
            except asyncio.TimeoutError:
                break
            recv = time.time_ns() // 1000
            if isinstance(msg, bytes):
                h = P.decode_header(msg)
                n = P.SPIKES_HEAD.unpack_from(msg, P.HEADER_LEN)[0] if h.kind == P.KIND_SPIKES else 0
                rows.append((h.update, h.emit_us, h.sent_us, recv, n, h.seq, h.dropped))
    return np.array(rows, dtype=np.int64).reshape(-1, 7)


def _client_process(addr: str, n: int, seconds: float, sub: dict, out: mp.Queue) -> None:
    async def main():
        return await asyncio.gather(*(_one_client(addr, seconds, sub) for _ in range(n)))

    out.put(asyncio.run(main()))


def _run_clients(addrs: str | list[str], n: int, seconds: float, processes: int, sub: dict | None = None) -> list[np.ndarray]:
    """Rows of ``n`` clients in ``processes`` processes; process i connects to ``addrs[i % len(addrs)]``."""
    addrs = [addrs] if isinstance(addrs, str) else addrs
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    counts = [len(part) for part in np.array_split(np.arange(n), max(min(processes, n), min(len(addrs), n)))]
    procs = [ctx.Process(target=_client_process, args=(addrs[i % len(addrs)], k, seconds, sub or {}, q))
             for i, k in enumerate(counts)]
    for p in procs:
        p.start()
    results = [arr for _ in procs for arr in q.get(timeout=seconds + 120)]
    for p in procs:
        p.join(30)
    return results


# -- server side ---------------------------------------------------------------------------------------
def _stats_ms(x: np.ndarray) -> str:
    if x.size == 0:
        return "n/a"
    return f"{np.mean(x):7.2f} {np.percentile(x, 95):7.2f} {np.max(x):7.2f}"


def run(args: argparse.Namespace) -> int:
    from ..server.app import serving
    from ..server.service import Service
    from ..server.settings import RuntimeConfig, ServeSettings

    params = EncoderParams.load(args.params) if args.params else default_params()
    with tempfile.TemporaryDirectory() as state:
        settings = ServeSettings(state_dir=Path(state), params=args.params, queue_frames=256)
        svc = Service(settings, RuntimeConfig(taxels=args.taxels))
        log: dict[int, dict[str, np.ndarray]] = {}
        compute: list[float] = []
        deliver = svc._deliver

        def recording_deliver(upd):
            log[upd.update] = upd.latency_us
            compute.append(upd.compute_s)
            deliver(upd)

        svc._deliver = recording_deliver
        with contextlib.ExitStack() as stack:
            companions, nats_url = [], None
            if args.nats:
                from ..bridge.natsd import local_nats_server
                from ..bridge.publisher import NatsPublisher

                nats_url = stack.enter_context(local_nats_server())
                companions.append(NatsPublisher(svc, nats_url, BENCH_SENSOR))
            addr = stack.enter_context(serving(svc, companions=companions))
            time.sleep(1.0)
            print(f"TouchReal service benchmark: simulated e-skin, {args.taxels} taxel(s), update "
                  f"{params.preprocess.update_ms:g} ms ({1000 / params.preprocess.update_ms:.2f} Hz), windows "
                  + ", ".join(f"{c} {params.window_ms(c):g} ms" for c in params.classes)
                  + "; algorithmic latency " + ", ".join(f"{c} {v / 1000:.1f} ms" for c, v in svc.latency_us().items()))
            _part1(addr, args, log, compute)
            direct_counts = args.subscribers or (args.nats_subscribers if args.nats else "1,10,100")
            _part2([addr], args, direct_counts, "2. Fan-out, direct (receipt minus emission), all classes and taxels")
            if nats_url:
                gateways = [stack.enter_context(_gateway_process(nats_url)) for _ in range(2)]
                _part2(gateways, args, args.nats_subscribers, "2b. Fan-out through NATS and 2 gateways (receipt minus "
                       "the publisher's emission), all classes and taxels")
                _decoded([("direct", addr), ("NATS + gateway", gateways[0])], args)
    _part3(params, args.taxels)
    return 0


def _part1(addr: str, args, log: dict, compute: list) -> None:
    compute.clear()
    (rows,) = _run_clients(addr, 1, args.seconds, 1)
    ms = np.array(compute[3:]) * 1000
    print(f"\n1. End-to-end latency, 1 subscriber, {args.seconds:g} s (ms; mean p95 max)")
    print(f"   compute per update: mean {ms.mean():.3f}, p95 {np.percentile(ms, 95):.3f}, max {ms.max():.3f} ms")
    print("   class   acquisition -> frame sent      acquisition -> received    spikes")
    for c in CLASSES:
        sent, recv = [], []
        for update, emit, s, r, *_ in rows:
            lat = log.get(int(update), {}).get(c)
            if lat is not None and lat.size:
                sent.append(lat * 1000 + (s - emit) / 1000)
                recv.append(lat * 1000 + (r - emit) / 1000)
        sent_a = np.concatenate(sent) if sent else np.zeros(0)
        recv_a = np.concatenate(recv) if recv else np.zeros(0)
        print(f"   {c:>4}   {_stats_ms(sent_a):>26}   {_stats_ms(recv_a):>26}   {sent_a.size:6d}")


@contextlib.contextmanager
def _gateway_process(nats_url: str):
    """A ``touchreal gateway`` process on a free loopback port; yields its address once ready."""
    import httpx

    from ..bridge.natsd import free_port

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "touchreal", "gateway", "--nats", nats_url, "--sensor-id",
                             BENCH_SENSOR, "--port", str(port)], stdout=subprocess.DEVNULL)
    addr = f"127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://{addr}/v1/ready", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the gateway did not become ready")
            time.sleep(0.2)
        yield addr
    finally:
        proc.terminate()
        proc.wait(15)


def _part2(addrs: list[str], args, subscribers: str, title: str) -> None:
    counts = [int(x) for x in subscribers.split(",") if x]
    print(f"\n{title}")
    print("   subscribers  seconds  events/s/client  frames/s/client  p50 ms  p99 ms  max ms  dropped")
    for n in counts:
        seconds = args.soak_seconds if n == counts[-1] else args.seconds
        res = _run_clients(addrs, n, seconds, max(args.processes, len(addrs)))
        fan = np.concatenate([(r[:, 3] - r[:, 1]) / 1000 for r in res if r.size])
        ev = np.mean([r[:, 4].sum() / seconds for r in res])
        fr = np.mean([r.shape[0] / seconds for r in res])
        dropped = sum(int(r[-1, 6]) for r in res if r.size)
        gaps = sum(int(np.sum(np.diff(r[:, 5]) != 1)) for r in res if r.shape[0] > 1)
        print(f"   {n:11d}  {seconds:7.0f}  {ev:15.1f}  {fr:15.1f}  {np.percentile(fan, 50):6.2f}  "
              f"{np.percentile(fan, 99):6.2f}  {fan.max():6.1f}  {dropped} (seq gaps {gaps})")


def _decoded(paths: list[tuple[str, str]], args, decoder: str = "force") -> None:
    """Decoded outputs (``decoder``, every taxel), one subscriber on each path in turn."""
    print(f"\n2c. Decoded outputs ({decoder}, 1 subscriber, {args.seconds:g} s; receipt minus emission)")
    print("   path               frames/s  p50 ms  p99 ms  max ms  dropped")
    for label, addr in paths:
        (r,) = _run_clients(addr, 1, args.seconds, 1, {"streams": ["decoded"], "decoders": [decoder]})
        if not r.size:
            print(f"   {label:<17}  no frames")
            continue
        fan = (r[:, 3] - r[:, 1]) / 1000
        print(f"   {label:<17}  {r.shape[0] / args.seconds:8.1f}  {np.percentile(fan, 50):6.2f}  "
              f"{np.percentile(fan, 99):6.2f}  {fan.max():6.1f}  {int(r[-1, 6])}")


def _part3(params: EncoderParams, n_taxels: int) -> None:
    from ..sensing.scene import SceneSource, taxel_grid
    from ..stream import StreamEncoder

    n = max(n_taxels, 16)
    update_s = params.preprocess.update_ms / 1000.0
    src = SceneSource(taxels_xy_mm=taxel_grid(n), seed=1)
    chunks = [src.read(update_s) for _ in range(300)]
    no_pvdf = params.model_copy(deep=True)
    sa1 = no_pvdf.classes["SA1"]
    sa1.weights = sa1.weights[:4] + [0.0] * 4
    cases = [
        ("all classes, all taxels", params, {c: range(n) for c in params.classes}),
        ("SA1 only, all taxels", params, {"SA1": range(n)}),
        ("all classes, 1 taxel", params, {c: [0] for c in params.classes}),
        ("SA1 without PVDF weights", no_pvdf, {"SA1": range(n)}),
        ("nobody subscribed", params, {}),
    ]
    print(f"\n3. Computing only what is demanded ({n} taxels; ms per update, mean over {len(chunks) - 20} after warm-up)")
    base = None
    for name, p, demand in cases:
        se = StreamEncoder(p, n)
        se.set_active({c: list(t) for c, t in demand.items()})
        times = []
        for i, ch in enumerate(chunks):
            t0 = time.perf_counter()
            se.process(ch)
            if i >= 20:
                times.append(time.perf_counter() - t0)
        mean = 1000 * float(np.mean(times))
        base = base or mean
        print(f"   {name:<28} {mean:7.3f} ms  ({100 * (1 - mean / base):5.1f} % saved)")
