"""A real uvicorn server on 127.0.0.1 (a free port, its own thread) and small WebSocket helpers."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import websockets
from touchreal_client import protocol as P

from touchreal.server.app import serving
from touchreal.server.service import Service
from touchreal.server.settings import RuntimeConfig, ServeSettings


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


async def collect(ws, seconds: float, until=None, clock: list | None = None) -> list:
    """Frames (decoded) and control messages (dicts) received for ``seconds`` or until ``until(frames)``
    is true; ``clock`` messages go to the list ``clock`` if one is given, else are left out."""
    frames: list = []
    end = time.monotonic() + seconds
    while time.monotonic() < end and not (until and until(frames)):
        try:
            msg = await asyncio.wait_for(ws.recv(), max(end - time.monotonic(), 0.01))
        except asyncio.TimeoutError:
            break
        if isinstance(msg, bytes):
            frames.append(P.decode_frame(msg))
        else:
            m = json.loads(msg)
            if m["type"] == "clock":
                if clock is not None:
                    clock.append(m)
                continue
            frames.append(P.frame_from_json(m) if m["type"] in ("spikes", "channels", "decoded") else m)
    return frames


def n_spikes(frames: list) -> int:
    """How many of ``collect``'s items are spikes frames (it also returns JSON messages such as ``clock``)."""
    return sum(isinstance(f, P.SpikesFrame) for f in frames)


async def stall_one_of_two(addr: str, hub, metrics, seconds: float) -> tuple[list, object, bool]:
    """Two clients subscribe to a heavy stream (5 kHz channels); one never reads (4 KiB receive buffer).

    Returns the frames the reading client got until the hub closed the stalled one (or ``seconds``),
    the close frame the stalled client finally reads, and whether it left the hub.
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
        frames = await collect(good, seconds, lambda fs: metrics.kicked._value.get() >= 1 and len(fs) > 100)
        gone = stalled_id not in hub.subscribers
        try:  # the stalled client now reads what was buffered, then its close
            while True:
                await asyncio.wait_for(stalled.recv(), 10)
        except websockets.ConnectionClosed as closed:
            return frames, closed.rcvd, gone


async def until(predicate, seconds: float, what: str) -> None:
    """Poll ``predicate()`` every 20 ms until it is true; fail naming ``what`` after ``seconds``."""
    end = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"not within {seconds} s: {what}")
        await asyncio.sleep(0.02)


def wait_until(predicate, seconds: float, what: str) -> None:
    """:func:`until` for synchronous code."""
    end = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"not within {seconds} s: {what}")
        time.sleep(0.02)
