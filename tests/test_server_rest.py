"""The /v1 REST surface against a real uvicorn server on 127.0.0.1 (httpx), plus schemathesis."""

from __future__ import annotations

import asyncio
import json
import os

import httpx
import schemathesis
from hypothesis import HealthCheck, given, settings
from server_harness import connect, hello_and_subscribe, running_server, wait_until

from touchreal.params import default_params
from touchreal.server.service import Service
from touchreal.server.settings import RuntimeConfig, ServeSettings


def _params_json(**class_updates) -> dict:
    d = json.loads(default_params().to_json())
    for cls, upd in class_updates.items():
        d["classes"][cls].update(upd)
    return d


def test_a_source_still_opening_is_reported_as_opening_not_failed(tmp_path):
    """Between the service's start and its first source open (the JIT warm-up runs first) the status says
    the source is opening; ``failed`` is for a source that could not open."""
    svc = Service(ServeSettings(state_dir=tmp_path / "state"), RuntimeConfig())
    assert svc.view.status()["source"] == {"spec": "sim", "state": "opening", "error": None}
    assert svc.view.ready() == (False, "warming up (compiling the pipeline, opening the source)")
    svc.source_error = "no such device"
    svc.opened.set()
    assert svc.view.status()["source"] == {"spec": "sim", "state": "failed", "error": "no such device"}


def test_health_ready_status_and_metrics(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/health").json() == {"status": "ok", "session": svc.session, "reason": None}
            r = wait_until(lambda: (got := http.get("/v1/ready")).status_code == 200 and got, 20, "ready")
            assert r.json()["ready"] is True
            st = http.get("/v1/status").json()
            assert st["source"]["state"] == "streaming" and st["pipeline"]["state"] in ("idle", "starting")
            # the simulated skin's build runs on 50 Hz mains: its stream resolves that from its first 0.1 s
            wait_until(lambda: http.get("/v1/status").json()["pipeline"]["mains_hz"] == 50.0, 20, "mains resolved")
            text = http.get("/metrics").text
    for name in ("touchreal_update_compute_seconds", "touchreal_latency_seconds", "touchreal_events_total",
                 "touchreal_clients_connected", "touchreal_input_faults", "touchreal_ready"):
        assert name in text


def test_ready_is_false_when_the_source_cannot_open(tmp_path):
    with running_server(tmp_path, RuntimeConfig(source="replay:/nonexistent/dataset")) as (addr, svc):
        r = httpx.get(f"http://{addr}/v1/ready")
        assert r.status_code == 503 and "not found" in r.json()["reason"]
        assert httpx.get(f"http://{addr}/v1/health").status_code == 200


def test_params_upload_validation_persistence_history_and_rollback(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        with httpx.Client(base_url=f"http://{addr}") as http:
            first = http.get("/v1/params").json()
            assert first["rev"] == 1 and first["params"]["schema"] == "touchreal.params"
            bad = _params_json(SA1={"tau_ms": -1.0, "weights": [1.0]}, RA={"colour": "red"})
            r = http.put("/v1/params", json=bad)
            assert r.status_code == 422
            locs = {".".join(map(str, e["loc"])) for e in r.json()["detail"]}
            assert {"body.classes.SA1.tau_ms", "body.classes.SA1.weights", "body.classes.RA.colour"} <= locs
            assert http.get("/v1/params").json()["rev"] == 1  # the old set stays in force
            good = _params_json(SA1={"tau_ms": 3.0})
            r = http.put("/v1/params", json=good)
            assert r.status_code == 200 and r.json()["rev"] == 2
            assert http.get("/v1/params").json()["params"]["classes"]["SA1"]["tau_ms"] == 3.0
            hist = http.get("/v1/params/history").json()
            assert hist["active"] == 2 and [h["origin"] for h in hist["revisions"]] == ["shipped", "upload"]
            assert http.post("/v1/params/rollback", json={"rev": 99}).status_code == 404
            r = http.post("/v1/params/rollback", json={"rev": 1})
            assert r.status_code == 200 and r.json()["rev"] == 3 and r.json()["sha256"] == first["sha256"]
    # persisted across a restart of the service with the same state directory
    with running_server(tmp_path) as (addr, svc):
        info = httpx.get(f"http://{addr}/v1/params").json()
        assert info["rev"] == 3 and info["sha256"] == first["sha256"]


def test_write_endpoints_need_the_token_reads_stay_open(tmp_path):
    with running_server(tmp_path, token="s3cret") as (addr, svc):
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/config").status_code == 200 and http.get("/v1/params").status_code == 200
            body = _params_json()
            assert http.put("/v1/params", json=body).status_code == 401
            assert http.put("/v1/params", json=body, headers={"Authorization": "Bearer nope"}).status_code == 401
            assert http.patch("/v1/config", json={"classes": ["SA1"]}).status_code == 401
            assert http.post("/v1/params/rollback", json={"rev": 1}).status_code == 401
            ok = {"Authorization": "Bearer s3cret"}
            assert http.put("/v1/params", json=body, headers=ok).status_code == 200
            assert http.patch("/v1/config", json={"classes": ["SA1"]}, headers=ok).status_code == 200


def test_config_patch_restarts_what_it_must(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        with httpx.Client(base_url=f"http://{addr}") as http:
            cfg = http.get("/v1/config").json()
            assert cfg["source"] == "sim" and cfg["taxels"] == 1 and cfg["window_ms"] == 128.0
            r = http.patch("/v1/config", json={"taxels": 4})
            assert r.status_code == 200 and r.json()["restarted"] == ["source"]
            r = http.patch("/v1/config", json={"window_ms": 64.0})
            assert r.json()["restarted"] == ["pipeline"] and r.json()["config"]["window_ms"] == 64.0
            assert http.get("/v1/params").json()["rev"] == 2
            assert http.patch("/v1/config", json={"source": "webcam"}).status_code == 400
            assert http.patch("/v1/config", json={"classes": ["SA2"]}).status_code == 400
            assert http.patch("/v1/config", json={"taxels": 0}).status_code == 422
            assert http.patch("/v1/config", json={"colour": "red"}).status_code == 422

        async def go():
            async with connect(addr) as ws:
                hello, _ = await hello_and_subscribe(ws)
                return hello

        hello = asyncio.run(asyncio.wait_for(go(), 30))
    assert len(hello["taxels"]) == 4 and hello["window_us"]["PC"] == 64000  # classes without their own window


def test_openapi_fuzz_finds_no_server_error(tmp_path):
    """schemathesis generates requests for every operation of the OpenAPI document: none gets a 5xx."""
    with running_server(tmp_path) as (addr, svc):
        schema = schemathesis.openapi.from_url(f"http://{addr}/openapi.json")
        operations = [result.ok() for result in schema.get_all_operations()]
        assert len(operations) >= 9
        for op in operations:

            @given(op.as_strategy())
            @settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), database=None)
            def check(case):
                response = case.call()
                assert response.status_code < 500, (case.method, case.path, case.body, response.text[:300])

            check()
        assert svc.runtime is not None and svc.runtime.state != "failed"


def test_the_simulated_skins_process_lives_as_long_as_its_source(tmp_path):
    with running_server(tmp_path) as (addr, svc):
        first = svc.runtime.source.hops._proc
        assert first.is_alive() and first.pid != os.getpid()
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.patch("/v1/config", json={"taxels": 4}).json()["restarted"] == ["source"]
        second = svc.runtime.source.hops._proc
        assert not first.is_alive() and first.exitcode is not None  # the reopened source ended the old one
        assert second.is_alive() and svc.runtime.source.n_taxels == 4
    second.join(10.0)
    assert not second.is_alive()  # and the service's stop ends its own
