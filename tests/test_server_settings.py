"""`touchreal serve` settings through one model (flags, TOUCHREAL_* variables, the generated doc)
and the HTTP server's connection limits, against the real command and a real server on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from server_harness import free_port, running_server
from waiting import wait_until

from touchreal.cli import build_parser
from touchreal.commands.serve import settings_from
from touchreal.server.settings import ServeSettings
from touchreal.commands.settings_doc import TABLES, begin, render

REPO = Path(__file__).resolve().parents[1]


def test_every_setting_is_a_serve_flag_and_an_environment_variable(monkeypatch):
    serve = build_parser()._subparsers._group_actions[0].choices["serve"]
    flags = {opt for action in serve._actions for opt in action.option_strings}
    for name in ServeSettings.model_fields:
        assert "--" + name.replace("_", "-") in flags
    for name in ("source", "taxels", "speed", "loop", "publish", "sensor_id", "log_level"):  # issue 20's list
        assert name in ServeSettings.model_fields
    env = {"TOUCHREAL_SOURCE": "replay:/data/ds", "TOUCHREAL_TAXELS": "3", "TOUCHREAL_SPEED": "2.5",
           "TOUCHREAL_LOOP": "true", "TOUCHREAL_PUBLISH": "nats://127.0.0.1:4222", "TOUCHREAL_SENSOR_ID": "lab-1",
           "TOUCHREAL_LOG_LEVEL": "info", "TOUCHREAL_ALLOWED_HOSTS": "127.0.0.1, touchreal.example"}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    s = settings_from(build_parser().parse_args(["serve", "--taxels", "5", "--no-loop"]))
    assert (s.source, s.taxels, s.speed, s.loop, s.publish, s.sensor_id, s.log_level) == \
        ("replay:/data/ds", 5, 2.5, False, "nats://127.0.0.1:4222", "lab-1", "info")  # flags win over the environment
    assert s.allowed_hosts == ["127.0.0.1", "touchreal.example"]
    monkeypatch.setenv("TOUCHREAL_TOKEN", "")
    assert ServeSettings().token is None  # compose passes "" when unset: no token


def test_the_settings_tables_in_the_docs_are_current():
    for doc, models in TABLES.items():
        text = (REPO / doc).read_text()
        for model, prefix in models:
            assert f"{begin(model)}\n{render(model, prefix)}\n" in text, "run: python -m touchreal.commands.settings_doc"


def test_every_gateway_setting_is_a_flag_and_an_environment_variable(monkeypatch):
    from touchreal.bridge.auth import NatsAuth
    from touchreal.bridge.settings import GatewaySettings
    from touchreal.commands.flags import model_from_args

    gateway = build_parser()._subparsers._group_actions[0].choices["gateway"]
    flags = {opt for action in gateway._actions for opt in action.option_strings}
    assert {"--" + n.replace("_", "-") for n in GatewaySettings.model_fields} <= flags
    assert {"--nats-" + n.replace("_", "-") for n in NatsAuth.model_fields} <= flags
    assert set(ServeSettings.model_fields) & set(GatewaySettings.model_fields) >= {"queue_frames", "max_clients",
                                                                                   "allowed_hosts", "ping_timeout_s"}
    monkeypatch.setenv("TOUCHREAL_GATEWAY_SENSOR_ID", "lab-2")
    monkeypatch.setenv("TOUCHREAL_GATEWAY_MAX_CLIENTS", "7")
    monkeypatch.setenv("TOUCHREAL_NATS_USER", "gateway-1")
    args = build_parser().parse_args(["gateway", "--max-clients", "9", "--nats-password", "pw"])
    s, auth = model_from_args(GatewaySettings, args), model_from_args(NatsAuth, args, prefix="nats-")
    assert (s.sensor_id, s.max_clients, s.port) == ("lab-2", 9, 8766)  # flag over environment over default
    assert auth.user == "gateway-1" and auth.password.get_secret_value() == "pw"


def _serve(env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "touchreal", "serve"], env={**os.environ, **env},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_bad_setting_in_the_environment_stops_serve_with_one_clear_line(tmp_path):
    proc = _serve({"TOUCHREAL_SOURCE": "bogus", "TOUCHREAL_STATE_DIR": str(tmp_path)})
    out, err = proc.communicate(timeout=60)
    assert proc.returncode != 0 and "Traceback" not in err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and "source" in lines[0] and "bogus" in lines[0], err


def test_serve_takes_its_settings_from_the_environment_and_an_empty_token_is_no_token(tmp_path):
    port = free_port()
    proc = _serve({"TOUCHREAL_PORT": str(port), "TOUCHREAL_TAXELS": "3", "TOUCHREAL_TOKEN": "",
                   "TOUCHREAL_STATE_DIR": str(tmp_path), "TOUCHREAL_ALLOWED_HOSTS": "127.0.0.1,touchreal.example"})
    try:
        base = f"http://127.0.0.1:{port}"

        def config():
            try:
                return httpx.get(f"{base}/v1/config", timeout=2).json()
            except httpx.HTTPError:
                assert proc.poll() is None, proc.stderr.read()
                return None

        assert wait_until(config, 90, "serve to answer")["taxels"] == 3
        assert httpx.patch(f"{base}/v1/config", json={"classes": ["SA1", "RA"]}).status_code == 200  # no token
        assert httpx.get(f"{base}/v1/health", headers={"Host": "touchreal.example"}).status_code == 200
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert "token is empty" in err


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_connections_that_never_finish_their_headers_are_closed(tmp_path):
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard < 1500:
        pytest.skip(f"needs 1500 descriptors (hard limit {hard})")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 1500), hard))
    with running_server(tmp_path, header_timeout_s=3.0) as (addr, svc):
        host, port = addr.split(":")
        before = _fds()
        socks = []
        for _ in range(500):
            s = socket.create_connection((host, int(port)), timeout=10)
            s.sendall(b"GET /v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            socks.append(s)
        # both ends of each connection live in this process, once the server has accepted them all
        wait_until(lambda: _fds() >= before + 900, 10, "the server to accept the connections")
        t0 = time.monotonic()
        for s in socks:
            s.settimeout(max(30 - (time.monotonic() - t0), 0.1))
            assert s.recv(1) == b""  # the server closed it
            s.close()
        wait_until(lambda: _fds() <= before + 10, 10, "the server's descriptors to be released")
        # a normal client is unaffected, on a kept-alive connection too
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/health").status_code == 200
            assert http.get("/v1/health").status_code == 200


def test_connections_beyond_limit_concurrency_get_503(tmp_path):
    with running_server(tmp_path, limit_concurrency=10) as (addr, svc):
        host, port = addr.split(":")
        with httpx.Client(base_url=f"http://{addr}") as http:
            assert http.get("/v1/health").status_code == 200  # this connection is one of the 10
            idle = [socket.create_connection((host, int(port)), timeout=10) for _ in range(9)]
            try:
                wait_until(lambda: httpx.get(f"http://{addr}/v1/health").status_code == 503, 10, "the limit")
            finally:
                for s in idle:
                    s.close()
            wait_until(lambda: http.get("/v1/health").status_code == 200, 10, "room again")
