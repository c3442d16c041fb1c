"""Service benchmark: latency and fan-out of the running server (the paper's Table 4), and the saving
from computing only what subscribers need.

Part 1 starts the service on the simulated e-skin (uvicorn on 127.0.0.1, this process) for each of
``--latency-taxels`` and one WebSocket client in another process, written as a user would from
docs/stream-protocol.md: it syncs its clock with ``time`` exchanges, maps stamps with the ``clock``
messages, and reports per class the latency of every spike as it holds it: its receipt minus the
acquisition of the sample that caused it (stamp minus the class delay), p50/p95/max. Beside it: the
same from the server's side (to the frame leaving the encoder, ``touchreal_latency_seconds``), the
compute per update, and the clock model's check on the sim (each chunk in hand after its stated
acquisition: the skin simulation's compute plus the thread's wake-up; the time-sync offset).

Part 2 connects 1, 10 and 100 subscribers (client processes) and reports events/s received, the
fan-out latency (receipt minus ``emit_us``) p50/p99 in the steady state (from ``--settle-s`` after
every subscriber held a frame; the worst while they joined is shown apart) and frames dropped.
``--soak-seconds`` runs the last count for that long.

With ``--nats`` (needs Debian's ``nats-server``), part 2 runs again through NATS: the service
publishes (``--publish``), two ``touchreal gateway`` processes serve the subscribers (spread evenly
over both), all on loopback; the latency is the same receipt minus ``emit_us`` (the publisher's
encoder), so the broker hop and the gateway are included; then one subscriber to the decoded force
takes each path in turn (the decoder runs in the service; its outputs cross on ``decoded.force``).

``--skin`` runs only the whole service on a large skin instead (bench/serve_skin.py): the CPU time
of the ``touchreal serve`` process tree, activity-driven against ``--dense``.

Part 3 drives the pipeline directly and compares the compute time per update for what a demand
needs: everything, one class, one taxel of many, a PVDF-free class, and nobody.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..params import EncoderParams, default_params
from ..settings import CLASSES
from . import serve_skin

BENCH_SENSOR = "bench"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="length of each measurement (s)")
    p.add_argument("--subscribers", default=None, help="subscriber counts for the fan-out part (default 1,10,100; "
                   "with --nats the --nats-subscribers counts, so both paths are measured side by side)")
    p.add_argument("--soak-seconds", type=float, default=60.0, help="length of the largest fan-out run (s)")
    p.add_argument("--taxels", type=int, default=1, help="taxels of the simulated e-skin (part 3, and 2b with --nats)")
    p.add_argument("--fanout-taxels", default="1,256", help="taxel counts for the fan-out of spikes (part 2)")
    p.add_argument("--all-streams-subscribers", default="10,25,50,100",
                   help="subscriber counts for part 2d: every stream (spikes, channels, decoded) at the largest "
                   "--fanout-taxels (none given: --taxels); empty: skipped; the largest count served within 10 ms p99 is reported")
    p.add_argument("--latency-taxels", default="1,256", help="taxel counts for part 1 (comma-separated)")
    p.add_argument("--settle-s", type=float, default=1.0, help="part 2: the steady state starts this long after every "
                   "subscriber held its first frame; part 1: spikes caused this long after subscribing "
                   "or later are the steady state; those caused before (the start rebuilds every subscribed branch "
                   "from the raw history, a burst of compute with many taxels) are reported apart (max)")
    p.add_argument("--params", type=Path, default=None, help="parameter file (default: shipped)")
    p.add_argument("--processes", type=int, default=2, help="client processes for the fan-out part")
    p.add_argument("--nats", action="store_true", help="also measure fan-out through NATS and two gateways")
    p.add_argument("--nats-subscribers", default="1,100,300", help="subscriber counts through the gateways")
    serve_skin.add_arguments(p)
    p.add_argument("--url", default=None, help="measure an already running service (http://HOST:PORT) instead of "
                   "starting one: parts 1 (as its clients see it) and 2 only")


# -- client side (runs in child processes) -------------------------------------------------------------
async def _sync_clock(ws, clock, exchanges: int = 5) -> None:
    """NTP-style ``time`` exchanges before subscribing; the one with the least round trip sets the offset."""
    from touchreal_client import protocol as P

    best = None
    for i in range(exchanges):
        t0 = time.time_ns() // 1000
        await ws.send(json.dumps({"type": "time", "id": i, "t0_us": t0}))
        while True:
            m = json.loads(await ws.recv())
            if m["type"] == "time":
                break
            if m["type"] == "clock":
                clock.update(m)
        offset, delay = P.clock_offset(t0, m["t1_us"], m["t2_us"], time.time_ns() // 1000)
        if best is None or delay < best[1]:
            best = (offset, delay)
    clock.set_offset(best[0], best[1] / 2)


async def _one_client(addr: str, seconds: float, sub: dict, spikes: bool = False, settle_s: float = 0.0):
    """Rows (update, emit_us, sent_us, recv_us, n_events, seq, dropped) per spikes frame; with ``spikes``
    also per class the latency of every spike as received (us, clock model) whose cause was acquired
    ``settle_s`` or more after subscribing, the clock offset used, and per class the latencies of the
    spikes caused before."""
    import websockets
    from touchreal_client import protocol as P
    from touchreal_client.clock import ClockMap
    from touchreal_client.stats import spike_latency_us

    rows, lat, early = [], {c: [] for c in CLASSES}, {c: [] for c in CLASSES}
    clock = ClockMap()
    async with websockets.connect(f"ws://{addr}/v1/stream", compression=None, max_size=None) as ws:
        hello = json.loads(await ws.recv())
        clock.update(hello["clock"])
        if spikes:
            await _sync_clock(ws, clock)
        await ws.send(json.dumps({"type": "subscribe", **sub}))
        settled_us = time.time_ns() // 1000 + int(settle_s * 1e6)  # causes acquired from then on: steady state
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
                if spikes and n:
                    f = P.decode_frame(msg)
                    v = spike_latency_us(f, recv, clock, hello["delay_us"])
                    steady = recv - v >= settled_us
                    for i, c in enumerate(CLASSES):
                        lat[c].append(v[(f.cls == i) & steady])
                        early[c].append(v[(f.cls == i) & ~steady])
            elif spikes:
                m = json.loads(msg)
                if m["type"] == "clock":
                    clock.update(m)
                elif m["type"] == "hello":
                    hello = m
    rows = np.array(rows, dtype=np.int64).reshape(-1, 7)
    if not spikes:
        return rows
    joined = [{c: np.concatenate(v) if v else np.zeros(0) for c, v in d.items()} for d in (lat, early)]
    return rows, joined[0], clock.offset_us, joined[1]


class _LightClient(asyncio.Protocol):
    """A fan-out subscriber with as little client-side work per frame as the measurement allows, so
    that on a small machine the clients leave the CPU to the server: plain asyncio (no uvloop), the
    WebSocket protocol of ``websockets``' sans-I/O ``ClientProtocol`` straight on a transport (no task
    or queue per message), and per binary frame only its header read. Rows as :func:`_one_client`'s,
    with the frame's size in bytes appended; the receipt time is that of the read that completed it."""

    def __init__(self, addr: str, sub: dict, done: asyncio.Future):
        from websockets.client import ClientProtocol
        from websockets.uri import parse_uri

        self.ws = ClientProtocol(parse_uri(f"ws://{addr}/v1/stream"), max_size=None)
        self.sub, self.done = sub, done
        self.rows: list[tuple[int, ...]] = []
        self.transport: asyncio.Transport | None = None
        self.subscribed = False

    def connection_made(self, transport: asyncio.Transport) -> None:
        self.transport = transport
        self.ws.send_request(self.ws.connect())
        self._flush()

    def _flush(self) -> None:
        out = self.ws.data_to_send()
        if out and self.transport is not None:
            self.transport.write(b"".join(out))

    def data_received(self, data: bytes) -> None:
        from touchreal_client import protocol as P
        from websockets.frames import Opcode

        recv = time.time_ns() // 1000
        self.ws.receive_data(data)
        for ev in self.ws.events_received():
            if getattr(ev, "opcode", None) is Opcode.BINARY:
                h = P.decode_header(ev.data)
                n = P.SPIKES_HEAD.unpack_from(ev.data, P.HEADER_LEN)[0] if h.kind == P.KIND_SPIKES else 0
                self.rows.append((h.update, h.emit_us, h.sent_us, recv, n, h.seq, h.dropped, len(ev.data)))
            elif getattr(ev, "opcode", None) is Opcode.TEXT and not self.subscribed:  # the hello
                self.subscribed = True
                self.ws.send_text(json.dumps({"type": "subscribe", **self.sub}).encode())
        self._flush()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.done.done():
            self.done.set_result(None)


async def _light_clients(addr: str, n: int, seconds: float, sub: dict, settle_s: float) -> tuple[list, list]:
    """``n`` :class:`_LightClient` subscribers: connected one after another, then, once every one holds a
    frame, ``settle_s`` more before the ``seconds`` measured. Returns each one's rows of the measured
    seconds (the steady state) and of the joining before them (everybody connecting and subscribing
    while the others stream: reported apart)."""
    loop = asyncio.get_running_loop()
    host, port = addr.rsplit(":", 1)
    clients = []
    for _ in range(n):
        done = loop.create_future()
        _, c = await loop.create_connection(lambda: _LightClient(addr, sub, done), host, int(port))
        clients.append(c)
    deadline = time.monotonic() + 60.0
    while not all(c.rows for c in clients) and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    await asyncio.sleep(settle_s)
    marks = [len(c.rows) for c in clients]
    await asyncio.sleep(seconds)
    rows = [np.array(c.rows[m:], dtype=np.int64).reshape(-1, 8) for c, m in zip(clients, marks)]
    joining = [np.array(c.rows[:m], dtype=np.int64).reshape(-1, 8) for c, m in zip(clients, marks)]
    for c in clients:  # a closing handshake, so the server stops sending before the socket goes
        c.ws.send_close(1000)
        c._flush()
    await asyncio.wait([c.done for c in clients], timeout=10.0)
    for c in clients:
        c.transport.abort()
    return rows, joining


def _client_process(addr: str, n: int, seconds: float, sub: dict, out: mp.Queue, spikes: bool = False,
                    settle_s: float = 0.0) -> None:
    """Runs ``n`` clients; puts their results, the light clients' rows while joining (none for ``spikes``
    clients) and this process's CPU time (s) per second of the run."""
    async def main():
        if not spikes:
            return await _light_clients(addr, n, seconds, sub, settle_s)
        return await asyncio.gather(*(_one_client(addr, seconds, sub, spikes, settle_s) for _ in range(n))), []

    cpu0, t0 = time.process_time(), time.monotonic()
    results, joining = asyncio.run(main())
    out.put((results, joining, (time.process_time() - cpu0) / (time.monotonic() - t0)))


def _run_clients(addrs: str | list[str], n: int, seconds: float, processes: int, sub: dict | None = None,
                 spikes: bool = False, cpu: list[float] | None = None, settle_s: float = 0.0,
                 joining: list | None = None) -> list:
    """Rows of ``n`` clients in ``processes`` processes; process i connects to ``addrs[i % len(addrs)]``.
    ``cpu`` (if given) receives each process's CPU time per second (s/s), ``joining`` the light
    clients' rows from before their measured seconds."""
    addrs = [addrs] if isinstance(addrs, str) else addrs
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    counts = [len(part) for part in np.array_split(np.arange(n), max(min(processes, n), min(len(addrs), n)))]
    procs = [ctx.Process(target=_client_process, args=(addrs[i % len(addrs)], k, seconds, sub or {}, q, spikes, settle_s))
             for i, k in enumerate(counts)]
    for p in procs:
        p.start()
    results = []
    for _ in procs:
        rows, join_rows, cpu_s = q.get(timeout=seconds + settle_s + 180)
        results += rows
        if cpu is not None:
            cpu.append(cpu_s)
        if joining is not None:
            joining += join_rows
    for p in procs:
        p.join(30)
    return results


# -- server side ---------------------------------------------------------------------------------------
def _stats_ms(x: np.ndarray) -> str:
    """p50 / p95 / max."""
    if x.size == 0:
        return "n/a"
    return f"{np.median(x):7.2f} {np.percentile(x, 95):7.2f} {np.max(x):7.2f}"


def run(args: argparse.Namespace) -> int:
    if args.skin:
        return serve_skin.run(args)
    if args.url:
        return _run_remote(args)
    params = EncoderParams.load(args.params) if args.params else default_params()
    print(f"TouchReal service benchmark: simulated e-skin, update {params.preprocess.update_ms:g} ms "
          f"({1000 / params.preprocess.update_ms:.2f} Hz), windows "
          + ", ".join(f"{c} {params.window_ms(c):g} ms" for c in params.classes))
    print(f"\n1. Latency of each spike as a client holds it: receipt minus the acquisition of its causing sample "
          f"(clock model), 1 subscriber, {args.seconds:g} s; ms p50 / p95 / max")
    for n in [int(x) for x in args.latency_taxels.split(",") if x]:
        with _service(args, n) as (svc, log):
            addr = log["addr"]
            _part1(addr, args, svc, log, n)
    direct_counts = args.subscribers or (args.nats_subscribers if args.nats else "1,10,100")
    fan_taxels = [int(x) for x in args.fanout_taxels.split(",") if x]
    for n in fan_taxels:
        with _service(args, n) as (_, log):
            _part2([log["addr"]], args, direct_counts, f"2. Fan-out of spikes, direct (receipt minus emission), all "
                   f"classes and {n} taxel(s)", cpu=time.process_time)
    all_taxels = fan_taxels[-1] if fan_taxels else args.taxels
    if args.all_streams_subscribers:
        with _service(args, all_taxels) as (_, log):
            _part2([log["addr"]], args, args.all_streams_subscribers, f"2d. Every stream (spikes, channels, "
                   f"decoded), {all_taxels} taxel(s) (receipt minus emission)",
                   {"streams": ["spikes", "channels", "decoded"]}, cpu=time.process_time, within_ms=10.0)
    if args.nats:
        with _service(args, args.taxels) as (_, log), contextlib.ExitStack() as stack:
            gateways = [stack.enter_context(_gateway_process(log["nats"])) for _ in range(2)]
            _part2(gateways, args, args.nats_subscribers, "2b. Fan-out through NATS and 2 gateways (receipt minus "
                   "the publisher's emission), all classes and taxels")
            _decoded([("direct", log["addr"]), ("NATS + gateway", gateways[0])], args)
    _part3(params, args.taxels)
    return 0


def _run_remote(args: argparse.Namespace) -> int:
    """Parts 1 and 2 against a running service, from its clients' side only."""
    import httpx

    addr = args.url.split("://", 1)[-1].rstrip("/")
    status = httpx.get(f"http://{addr}/v1/status", timeout=10).json()
    print(f"TouchReal service benchmark against {args.url} (session {status.get('session')}, source "
          f"{status.get('source', {}).get('spec')}); server-side figures are not available from here")
    print(f"\n1. Latency of each spike as a client holds it (clock model), 1 subscriber, {args.seconds:g} s; ms p50 / p95 / max")
    ((_, lat, offset, early),) = _run_clients(addr, 1, args.seconds, 1, spikes=True, settle_s=args.settle_s)
    print(f"   client clock offset {offset:+.0f} us; spikes caused from {args.settle_s:g} s after subscribing "
          "(caused before: max)")
    for c in CLASSES:
        print(f"   {c:>4}   {_stats_ms(lat[c] / 1000):>28}   {lat[c].size:6d} spikes   ({_max_ms(early[c])})")
    _part2([addr], args, args.subscribers or "1,10,100", "2. Fan-out (receipt minus emission), what the service streams")
    _part2([addr], args, args.all_streams_subscribers, "2d. Every stream (spikes, channels, decoded; receipt minus "
           "emission)", {"streams": ["spikes", "channels", "decoded"]}, within_ms=10.0)
    return 0


@contextlib.contextmanager
def _service(args, n_taxels: int):
    """The service on the sim with ``n_taxels`` (and its NATS publisher with ``--nats``), ready; yields
    (service, log) where log holds its address and, per update, the server-side figures."""
    from ..server.app import serving
    from ..server.service import Service
    from ..server.settings import RuntimeConfig, ServeSettings

    with tempfile.TemporaryDirectory() as state, contextlib.ExitStack() as stack:
        settings = ServeSettings(state_dir=Path(state), params=args.params, queue_frames=256)
        svc = Service(settings, RuntimeConfig(taxels=n_taxels))
        log: dict = {"updates": []}
        deliver = svc._deliver

        def recording_deliver(upd, lost_before=None):  # server-side figures of each update: latency, compute, clock
            if upd.spikes:  # (not its decoders' outputs, which follow it)
                log["updates"].append((upd.latency_us, upd.compute_s, upd.acq_us, upd.clock))
            deliver(upd, lost_before)

        svc._deliver = recording_deliver
        companions = []
        if args.nats:
            from ..bridge.natsd import local_nats_server
            from ..bridge.publisher import NatsPublisher

            log["nats"] = stack.enter_context(local_nats_server())
            companions.append(NatsPublisher(svc, log["nats"], BENCH_SENSOR))
        log["addr"] = stack.enter_context(serving(svc, companions=companions))
        deadline = time.monotonic() + 120
        while not svc.view.ready()[0] and time.monotonic() < deadline:
            time.sleep(0.1)
        yield svc, log


def _part1(addr: str, args, svc, log: dict, n_taxels: int) -> None:
    log["updates"].clear()
    ((rows, lat, offset, early),) = _run_clients(addr, 1, args.seconds, 1, spikes=True, settle_s=args.settle_s)
    ups = [u for u in log["updates"] if u[2] >= log["updates"][0][2] + args.settle_s * 1e6]
    ms = np.array([u[1] for u in ups]) * 1000
    in_hand = np.array([(acq - clock.wall_us) / 1000 for _, _, acq, clock in ups if clock is not None])
    stated = svc.view.latency_us()
    print(f"\n   {n_taxels} taxel(s), caused from {args.settle_s:g} s after subscribing: compute per update mean {ms.mean():.2f}, "
          f"p95 {np.percentile(ms, 95):.2f} ms; client clock offset {offset:+.0f} us; chunk in hand after its stated "
          f"acquisition: min {in_hand.min():.2f}, median {np.median(in_hand):.2f}, p95 {np.percentile(in_hand, 95):.2f} ms")
    print("   class  look-ahead   -> leaves the encoder (server)    -> held by the client           spikes   "
          "(before: max)")
    for c in CLASSES:
        server = [u[0][c] * 1000 for u in ups if c in u[0]]
        srv = np.concatenate(server) if server else np.zeros(0)
        got = lat[c] / 1000
        print(f"   {c:>4}   {stated.get(c, 0) / 1000:7.1f}   {_stats_ms(srv):>28}   {_stats_ms(got):>28}   {got.size:6d}   "
              f"({_max_ms(early[c])})")


def _max_ms(lat_us: np.ndarray) -> str:
    return f"{lat_us.max() / 1000:.1f} ms" if lat_us.size else "none"


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


def _part2(addrs: list[str], args, subscribers: str, title: str, sub: dict | None = None,
           cpu: Callable[[], float] | None = None, within_ms: float | None = None) -> None:
    """One row per subscriber count: frames and bytes per second, receipt minus emission, drops; with
    ``cpu`` (the server's process time, when it runs in this process) its CPU per second and per frame
    sent; with ``within_ms`` the largest count whose p99 stayed within it. Latency figures are the
    steady state, from ``--settle-s`` after the last subscriber held its first frame; while the
    subscribers were joining (connecting and subscribing one after another) only the worst is shown.
    Drops and seq gaps count the whole run, joining included."""
    counts = [int(x) for x in subscribers.split(",") if x]
    print(f"\n{title}")
    print(f"   steady state: from {args.settle_s:g} s after every subscriber held a frame; 'joining max': the worst "
          "while they connected")
    print("   subscribers  seconds  frames/s/client  kB/s/client  MB/s total  p50 ms  p99 ms  max ms  joining max  "
          "server CPU  clients' CPU  dropped")
    served = None
    for n in counts:
        seconds = args.soak_seconds if n == counts[-1] else args.seconds
        cpu0 = cpu() if cpu else 0.0
        t0 = time.monotonic()
        client_cpu: list[float] = []
        joining: list[np.ndarray] = []
        res = _run_clients(addrs, n, seconds, max(args.processes, len(addrs)), sub, cpu=client_cpu,
                           settle_s=args.settle_s, joining=joining)
        cpu_s = (cpu() - cpu0) / (time.monotonic() - t0) if cpu else float("nan")
        fan = np.concatenate([(r[:, 3] - r[:, 1]) / 1000 for r in res if r.size])
        join_max = max(((r[:, 3] - r[:, 1]).max() / 1000 for r in joining if r.size), default=float("nan"))
        frames = sum(r.shape[0] for r in res)
        per_client = np.mean([r[:, 7].sum() / seconds for r in res]) / 1e3
        whole = [np.concatenate([j, r]) for j, r in zip(joining, res)]
        dropped = sum(int(r[-1, 6]) for r in whole if r.size)
        gaps = sum(int(np.sum(np.diff(r[:, 5]) != 1)) for r in whole if r.shape[0] > 1)
        p99 = np.percentile(fan, 99)
        load = f"{cpu_s * 1000:4.0f} ms/s, {cpu_s * seconds / max(frames, 1) * 1e6:4.1f} us/frame" if cpu else "n/a"
        print(f"   {n:11d}  {seconds:7.0f}  {frames / n / seconds:15.1f}  {per_client:11.1f}  {per_client * n / 1e3:10.2f}  "
              f"{np.percentile(fan, 50):6.2f}  {p99:6.2f}  {fan.max():6.1f}  {join_max:11.1f}  {load}  {sum(client_cpu) * 1000:4.0f} ms/s  "
              f"{dropped} (seq gaps {gaps})")
        if within_ms is not None and p99 <= within_ms:
            served = n
    if within_ms is not None:
        print(f"   served within {within_ms:g} ms p99: {served or 'none'} of the counts tried "
              f"(load average {', '.join(f'{x:.1f}' for x in os.getloadavg())})")


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
    from ..raw import taxel_grid
    from ..simulator.scene import SceneSource
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
