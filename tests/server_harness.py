"""A real uvicorn server on 127.0.0.1 (a free port, its own thread), small WebSocket helpers, and a
bridge (:mod:`touchreal_client.bridges`) running on its stream, in this event loop or as a command."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import waiting
import websockets
from touchreal_client import protocol as P
from touchreal_client.features import StreamBinner

from touchreal.server.app import serving
from touchreal.server.service import Service
from touchreal.server.settings import RuntimeConfig, ServeSettings

#: the tests' one waiting helper (tests/waiting.py), importable from here too
until, wait_until = waiting.until, waiting.wait_until


def needs_nats_server() -> None:
    """Skip the calling test where no nats-server binary is installed."""
    from touchreal.bridge import natsd

    if not natsd.available():
        pytest.skip("nats-server is not installed (Debian: apt-get install nats-server; .ci/run installs it)")


def free_port() -> int:
    """A loopback port free right now (for a server that must come back on the same port)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def running_server(state_dir: Path, config: RuntimeConfig | None = None, port: int = 0,
                   **settings) -> Iterator[tuple[str, Service]]:
    """Yields (``host:port``, the service) of a real server on a loopback port (0: a free one);
    stops it afterwards."""
    svc = Service(ServeSettings(host="127.0.0.1", port=port, state_dir=state_dir, **settings), config or RuntimeConfig())
    with serving(svc, port=port) as addr:
        yield addr, svc


def memory_mib(field: str = "VmRSS") -> float:
    """This process's ``VmRSS`` (now) or ``VmHWM`` (peak) from /proc/self/status (MiB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no {field} in /proc/self/status")


def connect(addr: str, **kw):
    """A client that, like ours, does not offer permessage-deflate unless asked (``compression=...``)."""
    return websockets.connect(f"ws://{addr}/v1/stream", **{"compression": None, "open_timeout": 10, **kw})


async def hello_and_subscribe(ws, **sub) -> tuple[dict, dict]:
    hello = json.loads(await ws.recv())
    await ws.send(json.dumps({"type": "subscribe", **sub}))
    while True:
        msg = await ws.recv()
        if isinstance(msg, str) and json.loads(msg)["type"] == "subscribed":
            return hello, json.loads(msg)


_POLL_S = 0.1  #: how often :func:`collect` tests its condition while no message arrives


async def collect(ws, seconds: float, until=None, clock: list | None = None, *, what: str | None = None,
                  into: list | None = None) -> list:
    """Frames (decoded) and control messages (dicts) received until ``until(frames)`` is true;
    ``clock`` messages go to the list ``clock`` if one is given, else are left out.

    With ``until``, ``seconds`` only bounds a failure: if ``until`` does not hold by then, AssertionError
    names ``what`` and what did arrive. Without it, everything received for ``seconds``: a fixed window,
    which a test may assert on only when it measures one (a rate), saying so. To check a property over
    a stretch of the stream, wait for the stretch: ``until=covers(seconds)``.
    ``into``: the list to append to (another coroutine's ``until`` may watch it); returned. ``until`` is
    tested on every message and every :data:`_POLL_S` without one.
    """
    frames: list = [] if into is None else into
    end = time.monotonic() + seconds
    while not (until and until(frames)):
        left = end - time.monotonic()
        if left <= 0:
            break
        try:  # in slices, so that a condition on more than the frames (a service's state) is seen soon after it holds
            msg = await asyncio.wait_for(ws.recv(), min(max(left, 0.01), _POLL_S))
        except asyncio.TimeoutError:
            continue
        if isinstance(msg, bytes):
            frames.append(P.decode_frame(msg))
        else:
            m = json.loads(msg)
            if m["type"] == "clock":
                if clock is not None:
                    clock.append(m)
                continue
            frames.append(P.frame_from_json(m) if m["type"] in ("spikes", "channels", "decoded") else m)
    else:
        return frames
    if until is not None:
        raise AssertionError(f"not within {seconds} s: {what or 'the awaited frames'}; got {_tally(frames)}")
    return frames


def _tally(frames: list) -> dict[str, int]:
    """How many of each kind of item ``collect`` got (for its failure message)."""
    out: dict[str, int] = {}
    for f in frames:
        kind = f.get("type", "?") if isinstance(f, dict) else type(f).__name__
        out[kind] = out.get(kind, 0) + 1
    return out


def _final_us(frame) -> int | None:
    """The sensor instant (us) a frame is final to: a spikes frame's latest class ``final_us``, a
    channels frame's last sample, a decoded frame's last step; None for anything else."""
    if isinstance(frame, P.SpikesFrame):
        return max((v for v in frame.final_us.values() if v is not None), default=None)
    if isinstance(frame, P.ChannelsFrame) and frame.data.shape[0]:
        return int(frame.t0_us) + (frame.data.shape[0] - 1) * int(frame.period_us)
    if isinstance(frame, P.DecodedFrame) and len(frame.t_us):
        return int(frame.t_us[-1])
    return None


def covers(seconds: float, where=None):
    """An ``until`` for :func:`collect`: true once the frames (those ``where(frame)`` accepts, if given)
    cover ``seconds`` of sensor time, from the earliest to the latest instant they are final to.

    What a test waits for when it checks a property over a stretch of the stream: the same stretch a
    fixed window of ``seconds`` gave on an unloaded machine (the sensor clock runs at 1x), however long
    a loaded one takes to deliver it. Incremental: it looks at each frame once, so one predicate
    serves one ``collect``.
    """
    seen, lo, hi = 0, None, None

    def enough(frames: list) -> bool:
        nonlocal seen, lo, hi
        for f in frames[seen:]:
            if where is None or where(f):
                t = _final_us(f)
                if t is not None:
                    lo, hi = (t, t) if lo is None else (min(lo, t), max(hi, t))
        seen = len(frames)
        return lo is not None and hi - lo >= seconds * 1e6

    return enough


def n_spikes(frames: list) -> int:
    """How many of ``collect``'s items are spikes frames (it also returns JSON messages such as ``clock``)."""
    return sum(isinstance(f, P.SpikesFrame) for f in frames)


async def stall_one_of_two(addr: str, hub, metrics, seconds: float) -> tuple[list, object, bool]:
    """Two clients subscribe to a heavy stream (5 kHz channels); one never reads (4 KiB receive buffer).

    Returns the frames the reading client got until the hub closed the stalled one (and it had more
    than 100; ``seconds`` bounds a failure), the close frame the stalled client finally reads, and
    whether it left the hub.
    """
    host, port = addr.split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    sub = {"streams": ["spikes", "channels"], "channels": {"decimation": 1}}
    async with connect(addr, sock=sock, max_size=None) as stalled, connect(addr, max_size=None) as good:
        await hello_and_subscribe(stalled, **sub)
        stalled_id = min(hub.subscribers)  # it connected first
        await hello_and_subscribe(good, **sub)
        frames = await collect(good, seconds, lambda fs: metrics.kicked._value.get() >= 1 and len(fs) > 100,
                               what="the hub closed the stalled client, and the other got over 100 frames")
        gone = stalled_id not in hub.subscribers
        try:  # the stalled client now reads what was buffered, then its close
            while True:
                await asyncio.wait_for(stalled.recv(), 10)
        except websockets.ConnectionClosed as closed:
            return frames, closed.rcvd, gone


async def status_when(addr: str, ok: Callable[[dict], bool], what: str, seconds: float = 20.0) -> dict:
    """The service's /v1/status once ``ok(status)`` holds (``until`` polls it); a failure names ``what``
    and the last demand seen."""
    last: dict[str, Any] = {}
    async with httpx.AsyncClient(base_url=f"http://{addr}") as http:

        async def get() -> dict | None:
            last.update((await http.get("/v1/status")).json())
            return dict(last) if ok(last) else None

        return await until(get, seconds, lambda: f"{what} (demand: {last.get('demand')})", interval=0.05)


def no_demand(status: dict) -> bool:
    """Whether the service's /v1/status shows no demand at all (no spikes, channels or decoders)."""
    d = status["demand"]
    return not d["columns"] and not d["channel_taxels"] and not d["decoders"]


def decoded_stream(state_dir: Path, decoders: list[str], seconds: float, enough: Callable[[list[str], list], bool],
                   what: str) -> tuple[bytes, dict, list[str], list]:
    """A real server's decoder ``decoders[0]`` as a client gets it over REST (ONNX bytes, metadata), and
    what the stream sends a client of SA1's and RA's spikes and ``decoders``' outputs until it covers
    ``seconds`` and ``enough(names, frames)`` holds (``names``: the hello's decoders, by the index a
    decoded frame gives; ``what`` names the wait). Returns (ONNX bytes, metadata, names, frames)."""
    with running_server(state_dir) as (addr, _svc):
        blob = httpx.get(f"http://{addr}/v1/decoders/{decoders[0]}/model.onnx").content
        meta = httpx.get(f"http://{addr}/v1/decoders/{decoders[0]}").json()
        cover = covers(seconds)

        async def go() -> tuple[list[str], list]:
            async with connect(addr) as ws:
                hello, _ = await hello_and_subscribe(ws, streams=["spikes", "decoded"], classes=["SA1", "RA"],
                                                     decoders=decoders)
                names = [d["name"] for d in hello["streams"]["decoded"]["decoders"]]
                return names, await collect(ws, 60.0, lambda fs: cover(fs) and enough(names, fs), what=what)

        names, frames = asyncio.run(asyncio.wait_for(go(), 90))
    return blob, meta, names, frames


def client_decoded(frames: list, meta: dict, start_us: int, step: Callable[[np.ndarray], float]) -> dict[int, float]:
    """A client's own decoding of the spikes frames among ``frames``: per decoding step (its time, us),
    ``step(counts)`` on taxel 0's counts from a :class:`StreamBinner` of the decoder's metadata ``meta``
    started at ``start_us``."""
    binner = StreamBinner.from_metadata(meta, [0], start_us=start_us)
    out = {}
    for f in frames:
        if isinstance(f, P.SpikesFrame):
            final = {c: v for c, v in f.final_us.items() if v is not None}
            for t, counts, _ in binner.push(f.t_us, f.taxel, f.cls, final):
                out[t] = step(counts)
    return out


async def cancelled(task: asyncio.Task) -> None:
    """Cancel ``task`` and wait until it has ended (whatever it raised)."""
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


@asynccontextmanager
async def bridge_running(bridge: Any) -> AsyncIterator[asyncio.Task]:
    """``bridge.run()`` as a task of this loop, entered once the bridge is ready (30 s at most) and
    cancelled on the way out; yields the task."""
    task = asyncio.create_task(bridge.run())
    try:
        await asyncio.wait_for(bridge.ready.wait(), 30)
        yield task
    finally:
        await cancelled(task)


@contextmanager
def bridge_command(*args: str, says: tuple[str, ...]) -> Iterator[subprocess.Popen]:
    """``touchreal bridge ARGS`` in another process, entered once it printed its first line (it prints one
    when it serves) and that line holds every text in ``says``; on the way out it must exit with 0 on
    SIGINT within 30 s (it is killed if it is still running after a failure)."""
    proc = subprocess.Popen([sys.executable, "-m", "touchreal", "bridge", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # EOF if the command died
        assert all(s in line for s in says), (line, proc.stderr.read() if proc.poll() is not None else "")
        yield proc
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
