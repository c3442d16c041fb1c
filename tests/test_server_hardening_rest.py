"""Hostile REST against a real uvicorn server on 127.0.0.1: parameter sets that do not run, pipeline
failures, persisted bad sets, config patches that cannot be applied (issue 20)."""

from __future__ import annotations

import asyncio
import json
import logging
import select
import socket
from pathlib import Path

import httpx
import pytest
from helpers import synthetic_trial
from server_harness import collect, connect, hello_and_subscribe, memory_mib, n_spikes, running_server, wait_until
from touchreal_client import protocol as P

from touchreal.params import default_params
from touchreal.recording import write_dataset
from touchreal.server.params_store import ParamsStore


def params_json(**preprocess) -> dict:
    d = json.loads(default_params().to_json())
    d["preprocess"].update(preprocess)
    return d


#: valid field by field, but 19 notches of Q 0.5 make the PVDF filter blow up (non-finite channels)
UNSTABLE_NOTCHES = {"notch_q": 0.5001, "notch_harmonics": list(range(1, 20))}


def spikes_frames(addr: str, seconds: float = 20.0, **sub) -> list:
    """The first 5 spike frames a fresh client gets after a subscription (bare by default); ``seconds``
    bounds a failure."""

    async def go():
        async with connect(addr) as ws:
            await hello_and_subscribe(ws, **sub)
            got = await collect(ws, seconds, lambda fs: n_spikes(fs) >= 5, what="5 spikes frames")
            return [f for f in got if isinstance(f, P.SpikesFrame)]

    return asyncio.run(asyncio.wait_for(go(), seconds + 30))


def rev_of(frame) -> int:
    """The parameter revision a spikes frame was made by (0 for anything else)."""
    return frame.header.params_rev if isinstance(frame, P.SpikesFrame) else 0


def test_a_set_that_does_not_run_is_refused_naming_why_and_the_old_set_stays(tmp_path):
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        r = http.put("/v1/params", json=params_json(**UNSTABLE_NOTCHES))
        assert r.status_code == 422 and "non-finite channels" in r.json()["detail"]
        r = http.put("/v1/params", json=params_json(mains_hz=1e-300))
        assert r.status_code == 422
        assert [e["loc"] for e in r.json()["detail"]] == [["body", "preprocess", "mains_hz"]]
        assert http.get("/v1/params").json()["rev"] == 1
        assert http.get("/v1/health").json()["status"] == "ok"
        assert spikes_frames(addr)


def test_a_pipeline_failure_falls_back_to_the_last_good_revision_and_keeps_streaming(tmp_path):
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        good = http.put("/v1/params", json=params_json(st_alpha=0.4)).json()["rev"]
        assert spikes_frames(addr)  # revision 2 has run
        # what a set the dry run missed does: the old schema let mains_hz=1e-300 through (LinAlgError; held
        # fixed, as the stream would otherwise resolve the skin's 50 Hz mains and never build that notch)
        bad = svc.store.active.model_copy(update={"preprocess": svc.store.active.preprocess.model_copy(
            update={"mains_hz": 1e-300, "mains_candidates_hz": []})})
        svc.store.put(bad, "upload")

        async def stream_through_the_failure():
            async with connect(addr) as ws:
                await hello_and_subscribe(ws)
                return await collect(ws, 20.0, lambda fs: svc.store.fallback_reason is not None
                                     and sum(rev_of(f) == good + 2 for f in fs) >= 3,
                                     what="the fallback, and 3 frames of its copy")

        frames = asyncio.run(asyncio.wait_for(stream_through_the_failure(), 60))
        assert any(rev_of(f) == good + 2 for f in frames)  # the fallback copy streams
        health = http.get("/v1/health").json()
        assert health["status"] == "degraded" and "revision 3 failed in the pipeline: LinAlgError" in health["reason"]
        ready = http.get("/v1/ready")
        assert ready.status_code == 200 and ready.json()["reason"].startswith("degraded")
        st = http.get("/v1/status").json()
        assert st["pipeline"]["state"] in ("running", "idle") and "LinAlgError" in st["params"]["fallback"]
        hist = http.get("/v1/params/history").json()["revisions"]
        assert hist[-1]["origin"] == f"fallback:{good}" and hist[-1]["sha256"] == hist[good - 1]["sha256"]
        # a good upload clears the degraded state
        assert http.put("/v1/params", json=params_json()).status_code == 200
        assert http.get("/v1/health").json() == {"status": "ok", "session": svc.session, "reason": None}


def _persist(state_dir: Path, params: dict) -> None:
    """A state directory whose active revision 2 is ``params`` as raw JSON (as an older build wrote it)."""
    ParamsStore(state_dir)  # revision 1: shipped
    store_dir = state_dir / "params"
    (store_dir / "rev-000002.json").write_text(json.dumps(params))
    hist = json.loads((store_dir / "history.json").read_text())
    hist["revisions"].append({**hist["revisions"][0], "rev": 2, "origin": "upload"})
    hist["active"] = 2
    (store_dir / "history.json").write_text(json.dumps(hist))


def test_a_persisted_set_that_no_longer_validates_falls_back_at_start_and_says_so(tmp_path, caplog):
    _persist(tmp_path, params_json(mains_hz=1e-300))
    caplog.set_level(logging.ERROR, "touchreal.server")
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        wait_until(lambda: http.get("/v1/ready").status_code == 200, 20, "ready")
        health = http.get("/v1/health").json()
        assert health["status"] == "degraded" and "revision 2 cannot be used" in health["reason"]
        assert "preprocess.mains_hz" in health["reason"]
        assert http.get("/v1/params/history").json()["revisions"][-1]["origin"] == "fallback:1"
        assert spikes_frames(addr)
    assert any("revision 2 cannot be used" in r.getMessage() for r in caplog.records)


def test_a_persisted_set_that_does_not_run_falls_back_to_the_shipped_set_at_start(tmp_path):
    _persist(tmp_path, params_json(**UNSTABLE_NOTCHES))
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        wait_until(lambda: http.get("/v1/ready").status_code == 200, 20, "ready")
        health = http.get("/v1/health").json()
        assert health["status"] == "degraded" and "revision 2 does not run" in health["reason"]
        assert http.get("/v1/params").json()["params"] == json.loads(default_params().to_json())
        assert http.get("/v1/params/history").json()["revisions"][-1]["origin"] == "fallback:shipped"


def test_a_pc_only_set_serves_a_bare_subscription_with_what_it_has(tmp_path):
    d = json.loads(default_params().to_json())
    d["classes"] = {"PC": d["classes"]["PC"]}
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        assert http.put("/v1/params", json=d).status_code == 200
        frames = spikes_frames(addr)
        assert frames and all(rev_of(f) == 2 for f in frames[-2:])
        # the client has left (on the next 5 ms hop the pipeline idles): what counts is that it never failed
        assert svc.runtime.state in ("running", "idle") and svc.runtime.error is None
        assert {c for f in frames for c in f.cls.tolist()} <= {P.CLASSES.index("PC")}
        assert http.get("/v1/health").json()["status"] == "ok"


def test_config_patches_are_validated_and_a_source_that_cannot_open_keeps_the_old_one(tmp_path):
    not_a_dataset = tmp_path / "empty"
    not_a_dataset.mkdir()
    with running_server(tmp_path, data_roots=[tmp_path]) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        for body, field in [({"speed": 5e-324}, "speed"), ({"speed": 1e309}, "speed"), ({"loop": 0}, "loop"),
                            ({"taxels": True}, "taxels"), ({"update_ms": "32"}, "update_ms")]:
            r = http.patch("/v1/config", content=json.dumps(body), headers={"Content-Type": "application/json"})
            assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", field], (body, r.text)
        r = http.patch("/v1/config", json={"source": f"replay:{not_a_dataset}"})
        assert r.status_code == 409 and "the previous source 'sim' runs again" in r.json()["detail"]
        assert http.get("/v1/config").json()["source"] == "sim"
        wait_until(lambda: http.get("/v1/ready").status_code == 200, 20, "the old source to stream again")
        assert http.get("/v1/health").json()["status"] == "ok" and spikes_frames(addr)
        r = http.patch("/v1/config", json={"update_ms": 1.0, "window_ms": 512.0})
        assert r.status_code == 200 and r.json()["restarted"] == ["pipeline", "source"]


def send_raw(http: httpx.Client, method: str, path: str, text: str) -> httpx.Response:
    """A request whose body is ``text`` as given (NaN, Infinity, huge literals: what json= would refuse)."""
    return http.request(method, path, content=text.encode(), headers={"Content-Type": "application/json"})


def test_hostile_bodies_get_422_naming_the_field_never_500(tmp_path):
    nested = '{"a":' * 500 + "1" + "}" * 500
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        good = json.dumps(default_params().model_dump(by_alias=True, mode="json"))
        cases = [
            ("PUT", "/v1/params", '{"classes":{},"x":NaN}', ["body", "x"]),
            ("PUT", "/v1/params", good[:-1] + ', "provenance": {"p": ' + nested + "}}", ["body"]),
            ("PUT", "/v1/params", good[:-1] + ', "provenance": {"p": ' + '{"a":' * 9 + "1" + "}" * 9 + "}}",
             ["body", "provenance"]),
            ("PUT", "/v1/params", good[:-1] + ', "provenance": {"n": Infinity}}', ["body", "provenance"]),
            ("PATCH", "/v1/config", '{"speed":NaN}', ["body", "speed"]),
            ("PATCH", "/v1/config", '{"speed":-Infinity}', ["body", "speed"]),
            ("PATCH", "/v1/config", '{"loop":0}', ["body", "loop"]),
            ("PATCH", "/v1/config", '{"taxels":' + "9" * 900 + "}", ["body", "taxels"]),
            ("PATCH", "/v1/config", '{"taxels":' + "9" * 5000 + "}", ["body"]),
            ("PATCH", "/v1/config", "[" * 8000 + "]" * 8000, ["body"]),  # within the route's 16 KiB
            ("PUT", "/v1/params", "[" * 300000 + "]" * 300000, ["body"]),
            ("POST", "/v1/params/rollback", '{"rev":NaN}', ["body", "rev"]),
            ("POST", "/v1/params/rollback", '{"rev":1.0}', ["body", "rev"]),
        ]
        for method, path, text, loc in cases:
            r = send_raw(http, method, path, text)
            assert r.status_code == 422, (method, path, text[:80], r.status_code, r.text[:300])
            assert any(e["loc"][: len(loc)] == loc for e in r.json()["detail"]), (text[:80], r.json())
        d = json.loads(good)
        d["classes"]["SA1"]["i_sat"] = True
        r = http.put("/v1/params", json=d)
        assert r.status_code == 422 and ["body", "classes", "SA1", "i_sat"] in [e["loc"] for e in r.json()["detail"]]
        assert http.get("/v1/params").json()["rev"] == 1 and http.get("/v1/config").json()["loop"] is False
        assert http.get("/v1/health").json()["status"] == "ok"


def _stream_body(addr: str, head: str, chunk: bytes, total: int) -> tuple[str, int]:
    """Send ``head`` then up to ``total`` bytes of ``chunk``s while watching for the answer; returns the
    status line the server sent and how many body bytes it had been sent by then."""
    host, port = addr.split(":")
    sent = 0
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(head.encode())
        while sent < total:
            if select.select([sock], [], [], 0)[0]:
                break
            try:
                sock.sendall(chunk)
            except OSError:  # the server answered and closed: read what it said
                break
            sent += len(chunk)
        sock.settimeout(10)
        answer = b""
        while b"\r\n" not in answer:
            part = sock.recv(4096)
            if not part:
                break
            answer += part
    return answer.split(b"\r\n", 1)[0].decode(), sent


def test_a_200_mb_put_is_refused_before_it_is_read_and_rss_stays_flat(tmp_path):
    big = 200 * 1024 * 1024
    chunk = b" " * (256 * 1024)
    with running_server(tmp_path, token="s3cret") as (addr, svc):
        rss0 = memory_mib()
        head = (f"PUT /v1/params HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n"
                f"Content-Length: {big}\r\n\r\n")
        status, sent = _stream_body(addr, head, chunk, big)
        assert status.startswith("HTTP/1.1 401") and sent < big // 10
        # with the token, a declared 200 MB body is 413 at once
        status, sent = _stream_body(addr, head.replace("\r\n\r\n", "\r\nAuthorization: Bearer s3cret\r\n\r\n"),
                                    chunk, big)
        assert status.startswith("HTTP/1.1 413") and sent < big // 10
        # and so is one that does not say its size (chunked), once it passes the limit
        chunked = (f"PUT /v1/params HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n"
                   "Authorization: Bearer s3cret\r\nTransfer-Encoding: chunked\r\n\r\n")
        frame = f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
        status, sent = _stream_body(addr, chunked, frame, big)
        assert status.startswith("HTTP/1.1 413") and sent < big // 10
        grown = memory_mib() - rss0
        assert grown < 50, f"RSS grew by {grown:.0f} MB"
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/health").json()["status"] == "ok"


def test_sources_are_confined_to_device_paths_and_data_roots(tmp_path):
    state, roots, outside = tmp_path / "state", tmp_path / "roots", tmp_path / "outside"
    entries = [{"id": "a", "protocol": "ramp", "condition": "c", "repeat": 0, "params": {}, "onset_s": 0.3,
                "stim_end_s": 1.05}]
    for ds in (roots / "ds", outside / "ds", state / "datasets" / "ds"):
        write_dataset(ds, {"name": "t", "trials": entries}, {"a": synthetic_trial(duration_s=1.0)})
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.5)
    with running_server(state, data_roots=[roots]) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        refused = {f"serial:spy://loop://?file={victim}": "pyserial URLs are off",
                   f"serial:socket://127.0.0.1:{listener.getsockname()[1]}": "pyserial URLs are off",
                   f"serial:{victim}": "device path under /dev",
                   f"serial:{tmp_path}/no-such-tty": "device path under /dev",
                   f"replay:{outside / 'ds'}": "data roots",
                   f"replay:{outside / 'nothing-here'}": "data roots",
                   f"replay:{roots}/../outside/ds": "data roots"}
        answers = {}
        for spec, why in refused.items():
            r = http.patch("/v1/config", json={"source": spec})
            assert r.status_code == 403 and why in r.json()["detail"], (spec, r.text)
            answers.setdefault(why, set()).add(r.json()["detail"])
        assert all(len(a) == 1 for a in answers.values())  # the same words whether the path exists or not
        with pytest.raises(TimeoutError):
            listener.accept()  # nothing connected out
        assert victim.read_text() == "keep me"
        assert http.get("/v1/config").json()["source"] == "sim"
        for ds in (roots / "ds", state / "datasets" / "ds"):
            r = http.patch("/v1/config", json={"source": f"replay:{ds}", "speed": 4.0})
            assert r.status_code == 200 and r.json()["config"]["source"] == f"replay:{ds}"
    listener.close()
    with running_server(state, source_changes=False) as (addr, svc), httpx.Client(base_url=f"http://{addr}") as http:
        for body in ({"source": f"replay:{state / 'datasets' / 'ds'}"}, {"taxels": 2}, {"speed": 2.0}):
            r = http.patch("/v1/config", json=body)
            assert r.status_code == 403 and "source changes are off" in r.json()["detail"]
        assert http.patch("/v1/config", json={"classes": ["SA1"]}).status_code == 200


def _handshake_status(addr: str, **kw) -> int:
    """101 if /v1/stream accepts the handshake (and says hello), else the HTTP status it answered."""
    import websockets

    async def go():
        try:
            async with connect(addr, **kw) as ws:
                assert json.loads(await ws.recv())["type"] == "hello"
                return 101
        except websockets.InvalidStatus as exc:
            return exc.response.status_code

    return asyncio.run(asyncio.wait_for(go(), 30))


def test_dns_rebinding_gets_4xx_host_allowlist_and_origin_check(tmp_path):
    with running_server(tmp_path, allowed_origins=["http://app.example"]) as (addr, svc):
        port = addr.split(":")[1]
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/health").status_code == 200
            assert http.get("/v1/health", headers={"Host": f"localhost:{port}"}).status_code == 200
            assert http.get("/v1/health", headers={"Host": f"rebind.attacker.example:{port}"}).status_code == 400
            r = http.patch("/v1/config", json={"taxels": 2}, headers={"Host": "rebind.attacker.example"})
            assert r.status_code == 400 and http.get("/v1/config").json()["taxels"] == 1
        assert _handshake_status(addr) == 101  # no Origin: not a browser
        assert _handshake_status(addr, origin=f"http://{addr}") == 101  # the dashboard's own page
        assert _handshake_status(addr, origin="http://app.example") == 101  # listed
        assert _handshake_status(addr, origin="http://attacker.example") == 403
        assert _handshake_status(addr, origin=f"http://rebind.attacker.example:{port}",
                                 additional_headers={"Host": f"rebind.attacker.example:{port}"}) == 400
        assert not svc.hub.subscribers
    with running_server(tmp_path, allowed_hosts=["touchreal.example"]) as (addr, svc):
        assert httpx.get(f"http://{addr}/v1/health", headers={"Host": "touchreal.example"}).status_code == 200
        assert httpx.get(f"http://{addr}/v1/health").status_code == 400
