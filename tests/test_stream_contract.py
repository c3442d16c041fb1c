"""The machine-readable /v1/stream contract (touchreal_client.schema: AsyncAPI 3.0 + JSON Schemas)
against the real messages of a running server, validated with the ``jsonschema`` library."""

from __future__ import annotations

import asyncio
import copy
import json
import time
from typing import Any

import httpx
import jsonschema
import pytest
from server_harness import connect, running_server
from touchreal_client import protocol as P
from touchreal_client.schema import CLIENT_MESSAGES, SERVER_MESSAGES, asyncapi, message_schema, server_message_schema


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 60))


def validator(name: str) -> jsonschema.Draft7Validator:
    return jsonschema.Draft7Validator(message_schema(name))


def errors(name: str, msg: Any) -> list[str]:
    return [e.message for e in validator(name).iter_errors(msg)]


def test_the_service_serves_the_asyncapi_document_and_its_schemas_are_valid(server):
    addr, _ = server
    doc = httpx.get(f"http://{addr}/v1/asyncapi.json", timeout=10).json()
    assert doc == asyncapi(addr)  # the shipped document, naming the server that served it
    assert doc["asyncapi"] == "3.0.0" and doc["channels"]["stream"]["address"] == "/v1/stream"
    assert doc["servers"]["service"] == {**asyncapi()["servers"]["service"], "host": addr}
    schemas = doc["components"]["schemas"]
    for name, schema in schemas.items():
        jsonschema.Draft7Validator.check_schema(schema)
    # every message and operation reference resolves; every JSON message has its schema
    for name, m in doc["components"]["messages"].items():
        ref = m["payload"].get("$ref")
        assert ref is None or ref.removeprefix("#/components/schemas/") in schemas, name
    for op in doc["operations"].values():
        assert op["action"] in ("send", "receive") and op["channel"] == {"$ref": "#/channels/stream"}
        for ref in op["messages"]:
            assert ref["$ref"].removeprefix("#/channels/stream/messages/") in doc["channels"]["stream"]["messages"]
    assert set(SERVER_MESSAGES.values()) | set(CLIENT_MESSAGES.values()) <= set(schemas)
    # the close codes listed are exactly the protocol's
    codes = {int(c) for c in doc["channels"]["stream"]["x-close-codes"]}
    assert codes == {v for k, v in vars(P).items() if k.startswith("CLOSE_")}


async def _conversation(addr: str) -> tuple[list[Any], list[dict]]:
    """Everything a JSON-encoding client provokes in a few seconds: hello, clock, subscribed, a time
    reply, errors for a malformed and a refused message, and spikes/channels/decoded frames."""
    sent: list[dict] = []
    got: list[Any] = []
    async with connect(addr, max_size=None) as ws:
        async def send(msg: dict) -> None:
            sent.append(msg)
            await ws.send(json.dumps(msg))

        got.append(json.loads(await ws.recv()))
        await send({"type": "subscribe", "classes": ["XX"]})  # refused: unknown class
        await ws.send("{not json")
        await send({"type": "subscribe", "streams": ["decoded"], "decoders": ["no-such-decoder"]})  # not served
        await send({"type": "time", "id": 1, "t0_us": 123})
        await send({"type": "subscribe", "version": 1, "taxels": [0], "classes": ["SA1", "RA", "PC"],
                    "streams": ["spikes", "channels", "decoded"], "encoding": "json", "channels": {"decimation": 25},
                    "decoders": None})
        need = {"hello", "clock", "subscribed", "time", "error", "spikes", "channels", "decoded"}
        end = time.monotonic() + 30
        while not need <= {m.get("type") for m in got} or sum(m.get("type") == "error" for m in got) < 3:
            assert time.monotonic() < end, f"never got {need - {m.get('type') for m in got}}"
            msg = await asyncio.wait_for(ws.recv(), max(end - time.monotonic(), 0.1))
            assert isinstance(msg, str), "a JSON subscriber got a binary frame"
            got.append(json.loads(msg))
    return got, sent


def test_every_message_of_a_real_conversation_follows_its_schema(server):
    addr, _ = server
    got, sent = run(_conversation(addr))
    seen: dict[str, int] = {}
    for m in got:
        name = server_message_schema(m)
        assert not errors(name, m), (name, errors(name, m), json.dumps(m)[:500])
        seen[name] = seen.get(name, 0) + 1
    assert {"hello", "clock", "subscribed", "timeReply", "error", "spikesFrame", "channelsFrame", "decodedFrame"} <= set(seen)
    # what the client sent: the accepted messages follow their schemas, the refused subscribe does not
    for m in sent:
        name = CLIENT_MESSAGES[m["type"]]
        assert bool(errors(name, m)) == (m.get("classes") == ["XX"]), (m, errors(name, m))
    codes = [m["code"] for m in got if m["type"] == "error"]
    assert codes.count("bad_message") == 2 and codes.count("not_served") == 1, codes


def test_the_schemas_reject_what_the_protocol_does_not_allow(server):
    addr, svc = server
    hello = svc.view.hello()
    assert not errors("hello", hello)
    for broken in ({k: v for k, v in hello.items() if k != "session"}, {**hello, "classes": ["SA1", "XX"]},
                   {**hello, "clock": {"sensor_us": 1, "wall_us": 2}}):
        assert errors("hello", broken)
    spikes = {"seq": 0, "dropped": 0, "sent_us": 2, "type": "spikes", "update": 1, "emit_us": 1, "params_rev": 1,
              "flags": ["restarted"], "final_us": {"SA1": 10}, "t_us": [5], "taxel": [0], "class": ["SA1"]}
    assert not errors("spikesFrame", spikes)
    for change in ({"class": ["S1"]}, {"t_us": [-5]}, {"flags": ["odd"]}, {"final_us": {"XX": 1}}, {"seq": None}):
        assert errors("spikesFrame", {**copy.deepcopy(spikes), **change}), change
    assert errors("subscribe", {"type": "subscribe", "colour": "red"})  # the server refuses unknown fields too
    assert errors("clock", {"type": "clock", "sensor_us": 1, "wall_us": 2, "rate": 0, "error_us": 0, "epoch": 0})


def test_a_replay_to_its_end_follows_the_schemas_ended_included(tmp_path):
    from test_server_stream import _replay_dataset

    from touchreal.server.settings import RuntimeConfig

    ds, _ = _replay_dataset(tmp_path)
    with running_server(tmp_path / "state", RuntimeConfig(source=f"replay:{ds}", speed=8.0)) as (addr, svc):
        async def go() -> list[dict]:
            got: list[dict] = []
            async with connect(addr, max_size=None) as ws:
                got.append(json.loads(await ws.recv()))
                await ws.send(json.dumps({"type": "subscribe", "encoding": "json", "streams": ["spikes", "channels"]}))
                end = time.monotonic() + 40
                ended_at = None
                while time.monotonic() < end and not any(m.get("type") == "ended" for m in got):
                    if ended_at is None and svc.runtime.state == "ended":
                        ended_at = time.monotonic()
                    if ended_at is not None and time.monotonic() > ended_at + 3:
                        # a window, on purpose (a negative): no `ended` within 3 s of the source's end means
                        # this service sends none (skipped below)
                        break
                    try:
                        got.append(json.loads(await asyncio.wait_for(ws.recv(), 0.5)))
                    except asyncio.TimeoutError:
                        pass
            return got

        got = run(go())
    for m in got:
        name = server_message_schema(m)
        assert not errors(name, m), (name, errors(name, m), json.dumps(m)[:500])
    assert {"hello", "clock", "subscribed", "spikes", "channels"} <= {m["type"] for m in got}
    assert len({m["epoch"] for m in got if m["type"] == "clock"}) >= 2  # a clock point per replayed trial
    if not any(m["type"] == "ended" for m in got):
        pytest.skip("this service sends no `ended` message at the end of a replay yet (the replay-fit work); "
                    "everything else of the replay followed the schemas")
