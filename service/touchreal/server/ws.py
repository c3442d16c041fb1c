"""``/v1/stream``: the WebSocket layer over one :class:`~.hub.Subscriber` (docs/stream-protocol.md).

Two tasks per connection: this handler reads client messages, no faster than the connection's
:class:`~.budget.ControlBudget` allows, and a sender task is the only writer (control replies
first, then frames). A client that stalls is closed from here when the hub marks
it (``kicked``), even while the sender is stuck in a send.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketDisconnect
from touchreal_client import protocol as P

from .budget import ControlBudget
from .hub import Subscriber
from .runtime import wall_us
from .security import admit

log = logging.getLogger("touchreal.server")
router = APIRouter()
#: How long a close may wait for a stalled client's socket to take the close frame; afterwards the
#: transport is closed without it (the subscriber left the hub at once either way).
CLOSE_TIMEOUT_S = 30.0


def _dumps(msg: dict[str, Any]) -> str:
    return json.dumps(msg, separators=(",", ":"))


@router.websocket("/v1/stream")
async def stream(ws: WebSocket) -> None:
    if not await admit(ws):
        return
    service = ws.app.state.service
    hub = service.hub
    await ws.accept()
    if len(hub.subscribers) >= service.settings.max_clients:
        await ws.close(P.CLOSE_TRY_AGAIN, f"server full ({service.settings.max_clients} clients)")
        return
    sub = hub.add()
    service.metrics.clients.inc()
    view = ws.app.state.view
    sub.say(_dumps(view.hello()))
    clock = view.clock_message()
    if clock is not None:
        sub.say(clock)
    if service.ended is not None:
        sub.say(_dumps(service.ended))
    sender = asyncio.create_task(_send_loop(ws, sub))
    kicked = asyncio.create_task(sub.kicked.wait())
    close: tuple[int, str] | None = None
    try:
        close = await _receive_loop(ws, sub, service, sender, kicked)
    except WebSocketDisconnect:
        close = None
    finally:
        sender.cancel()
        kicked.cancel()
        hub.remove(sub)
        service.metrics.clients.dec()
        try:
            service.metrics.client_drops.remove(str(sub.id))
        except KeyError:  # never labelled: it dropped nothing
            pass
        if sub.kick is not None:
            (service.metrics.flooding if sub.kick[0] == P.CLOSE_FLOODING else service.metrics.kicked).inc()
            close = sub.kick
        if close is not None:
            try:
                await asyncio.wait_for(ws.close(*close), CLOSE_TIMEOUT_S)
            except Exception:  # the peer is gone or stuck: uvicorn tears the transport down
                pass


async def _receive_loop(ws: WebSocket, sub: Subscriber, service, sender: asyncio.Task,
                        kicked: asyncio.Task) -> tuple[int, str] | None:
    errors = 0
    budget = ControlBudget()
    wait = 0.0
    while True:
        if wait > 0:  # over its budget: the next message stays in the network until the budget refills
            done, _ = await asyncio.wait({sender, kicked}, timeout=wait, return_when=asyncio.FIRST_COMPLETED)
            if done:
                return sub.kick if kicked in done else None
        recv = asyncio.ensure_future(ws.receive())
        done, _ = await asyncio.wait({recv, sender, kicked}, return_when=asyncio.FIRST_COMPLETED)
        if recv not in done or len(done) > 1:  # a kick wins over a message that arrived with it
            recv.cancel()
            return sub.kick if kicked in done else None  # the sender ended: the socket is gone
        msg = recv.result()
        if msg["type"] == "websocket.disconnect":
            return None
        t1 = wall_us()
        text = msg.get("text")
        wait = budget.charge(len(text if text is not None else msg.get("bytes") or b""))
        try:
            if text is None:
                raise P.ProtocolError("binary messages from clients are not part of the protocol; send JSON text")
            m = P.parse_client_message(text)
            if m["type"] == "time":
                sub.say(_dumps(P.time_reply(m, t1, wall_us())))
            else:
                s = service.hub.admit(m)
                service.hub.subscribe(sub, s)
                sub.say(_dumps({"type": "subscribed", **{k: v for k, v in s.to_json().items() if k != "type"},
                                "latency_us": ws.app.state.view.latency_us()}))
            errors = 0
        except P.ProtocolError as exc:
            sub.say(_dumps(P.error_message(exc.code, str(exc))))
            if exc.code == "unsupported_version":
                await _drain_control(ws, sub)
                return P.CLOSE_UNSUPPORTED_VERSION, "unsupported protocol version"
            if exc.code == "too_big":
                await _drain_control(ws, sub)
                return P.CLOSE_TOO_BIG, "message too big"
            errors += 1
            if errors >= P.MAX_ERRORS_IN_A_ROW:
                await _drain_control(ws, sub)
                return P.CLOSE_TOO_MANY_ERRORS, f"{errors} malformed messages in a row"


async def _drain_control(ws: WebSocket, sub: Subscriber) -> None:
    """Give the sender a moment to deliver the error before the close."""
    for _ in range(20):
        if not sub.control:
            return
        await asyncio.sleep(0.01)


async def _send_loop(ws: WebSocket, sub: Subscriber) -> None:
    try:
        while True:
            await sub.wakeup.wait()
            sub.wakeup.clear()
            while sub.control or sub.queue or sub.after_frames:
                if sub.control:
                    await ws.send_text(sub.pop_control())
                    continue
                if not sub.queue:
                    await ws.send_text(sub.after_frames.popleft())
                    continue
                item = sub.next_frame()
                if item is None:  # every queued frame was stale (then what follows the frames goes out)
                    continue
                data, _ = sub.render(item)
                if isinstance(data, str):
                    await ws.send_text(data)
                else:
                    await ws.send_bytes(data)
    except (WebSocketDisconnect, RuntimeError, OSError):
        return
