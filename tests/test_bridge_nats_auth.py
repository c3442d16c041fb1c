"""NATS with authentication: a real nats-server started with the shipped deploy/nats/nats-server.conf
(users and subject permissions), the service's publisher and a gateway authenticating to it."""

from __future__ import annotations

import asyncio
import json
import secrets
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import nats
import nkeys
import pytest
from nats.errors import Error as NatsError
from server_harness import collect, connect, hello_and_subscribe, n_spikes, until, wait_until
from test_bridge_nats import SENSOR, gateway, publishing
from touchreal_client import protocol as P

from touchreal.bridge import natsd, subjects
from touchreal.bridge.auth import NatsAuth
from touchreal.bridge.demand import MAX_ANNOUNCEMENT_BYTES, MAX_GATEWAYS, Announced, announcement
from touchreal.bridge.gateway import Gateway, GatewaySettings, create_gateway_app
from touchreal.server.app import serving_app
from touchreal.server.settings import RuntimeConfig

CONF = Path(__file__).resolve().parents[1] / "deploy" / "nats" / "nats-server.conf"


@pytest.fixture
def broker() -> Iterator[tuple[str, NatsAuth, NatsAuth]]:
    """(URL, publisher credentials, gateway credentials) of a nats-server running the shipped config."""
    if not natsd.available():
        pytest.skip("nats-server is not installed (Debian: apt-get install nats-server; .ci/run installs it)")
    pw = {"TOUCHREAL_NATS_PUBLISHER_PASSWORD": "tr_" + secrets.token_hex(16), "TOUCHREAL_NATS_GATEWAY_PASSWORD": "tr_" + secrets.token_hex(16)}
    with natsd.local_nats_server(config=CONF, env=pw) as url:
        yield (url, NatsAuth(user="publisher", password=pw["TOUCHREAL_NATS_PUBLISHER_PASSWORD"]),
               NatsAuth(user="gateway", password=pw["TOUCHREAL_NATS_GATEWAY_PASSWORD"]))


def run(coro, timeout: float = 60.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))



async def _refused_publish(url: str, auth: NatsAuth, subject: str, payload: bytes) -> str:
    """Publish as ``auth`` where it may not; returns the broker's permissions error."""
    errors: list[str] = []

    async def on_error(exc):
        errors.append(str(exc))

    nc = await nats.connect(url, error_cb=on_error, max_reconnect_attempts=0, **auth.connect_options())
    try:
        await nc.publish(subject, payload)
        await nc.flush()
        await until(lambda: any("ermissions" in e for e in errors), 10, f"a permissions error for {subject}")
    finally:
        await nc.close()
    return next(e for e in errors if "ermissions" in e)


def test_authenticated_publisher_and_gateway_stream_and_nobody_else_gets_in(tmp_path, broker):
    url, pub_auth, gw_auth = broker
    with publishing(tmp_path, url, RuntimeConfig(taxels=2), publisher={"auth": pub_auth}) as (addr, svc, pub), \
            gateway(url, auth=gw_auth) as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                hello, _ = await hello_and_subscribe(ws, taxels=[1])
                frames = await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 30)
            with pytest.raises((NatsError, OSError)):  # no credentials: the broker refuses the connection
                await nats.connect(url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False)
            wrong = NatsAuth(user="gateway", password="not-the-password")
            with pytest.raises((NatsError, OSError)):
                await nats.connect(url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False,
                                   **wrong.connect_options())
            fake = announcement("intruder", Announced({c: [0, 1] for c in P.CLASSES}))
            refused = [await _refused_publish(url, pub_auth, subjects.demand(SENSOR), fake),  # publishers: no demand
                       await _refused_publish(url, gw_auth, subjects.frames(SENSOR), b"TR"),  # gateways: no frames
                       await _refused_publish(url, gw_auth, subjects.hello(SENSOR), b"{}")]  # nor hello announcements
            return hello, frames, refused

        hello, frames, refused = run(go())
        status = httpx.get(f"http://{addr}/v1/status").json()["nats"]
    spikes = [f for f in frames if isinstance(f, P.SpikesFrame)]
    assert hello["session"] == svc.session and len(spikes) >= 30
    seqs = [f.header.seq for f in spikes]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and all(set(f.taxel.tolist()) <= {1} for f in spikes)
    for error, subject in zip(refused, (subjects.demand(SENSOR), subjects.frames(SENSOR), subjects.hello(SENSOR))):
        assert subject in error.lower(), error  # each refusal names the subject it refused
    assert status["auth"] == "user publisher" and "intruder" not in status["gateways"]
    assert gw.status()["auth"] == "user gateway"
    assert pub_auth.password.get_secret_value() not in json.dumps(status)


def test_a_gateway_authenticates_with_an_nkey(tmp_path):
    if not natsd.available():
        pytest.skip("nats-server is not installed (Debian: apt-get install nats-server; .ci/run installs it)")
    seed = nkeys.encode_seed(secrets.token_bytes(32), nkeys.PREFIX_BYTE_USER)
    public = nkeys.from_seed(seed).public_key.decode()
    (tmp_path / "gateway.nk").write_bytes(seed)
    conf = tmp_path / "nats.conf"
    perms = CONF.read_text().split("authorization {", 1)[1].rsplit("users = [", 1)[0]  # the shipped permissions
    conf.write_text("authorization {" + perms + 'users = [\n{user: publisher, password: "p", permissions: $PUBLISHER}\n'
                    f'{{nkey: "{public}", permissions: $GATEWAY}}\n]\n}}\n')
    with natsd.local_nats_server(config=conf) as url, \
            publishing(tmp_path / "state", url, publisher={"auth": NatsAuth(user="publisher", password="p")}) as (_, svc, _p), \
            gateway(url, auth=NatsAuth(nkey=tmp_path / "gateway.nk")) as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                hello, _ = await hello_and_subscribe(ws)
                return hello, await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 10)

        hello, frames = run(go())
    assert hello["session"] == svc.session and n_spikes(frames) >= 10 and gw.status()["auth"].startswith("nkey ")


def test_demand_announcements_are_bounded_dropped_and_counted(tmp_path, broker):
    """100k fake gateway ids, oversized, malformed and out-of-range announcements: the publisher keeps
    at most MAX_GATEWAYS, counts every drop, and /v1/status stays small."""
    url, pub_auth, gw_auth = broker
    n_fake = 100_000
    with publishing(tmp_path, url, RuntimeConfig(taxels=4), publisher={"auth": pub_auth}) as (addr, svc, pub):

        async def go():
            nc = await nats.connect(url, **gw_auth.connect_options())
            subject = subjects.demand(SENSOR)
            one = Announced({"SA1": [0]})
            for i in range(n_fake):
                await nc.publish(subject, announcement(f"fake{i}", one, ttl_s=30.0))
            await nc.publish(subject, b"{" * 200 + b"}" * 200)
            await nc.publish(subject, b'{"gateway": "x", "ttl_ms": NaN, "columns": {}}')
            await nc.publish(subject, json.dumps({"gateway": "g.x", "ttl_ms": 1000, "columns": {}}).encode())
            await nc.publish(subject, json.dumps({"gateway": "big", "ttl_ms": 1000, "columns": {},
                                                  "channels": [0] * (MAX_ANNOUNCEMENT_BYTES // 2)}).encode())
            await nc.publish(subject, announcement("far", Announced({"PC": [4]})))
            await nc.publish(subject, announcement("long-ttl", one, ttl_s=3600.0))
            await nc.flush()
            await nc.close()
            seen = lambda: sum(pub.status()["demand_rejected"].values()) + len(pub.demand.gateways)  # noqa: E731
            await until(lambda: seen() >= n_fake + 6, 60, "every announcement handled")

        run(go(), 120)
        status = httpx.get(f"http://{addr}/v1/status")
        metrics = httpx.get(f"http://{addr}/metrics").text
        demand = dict(svc.hub.demand.columns)
    nats_status = status.json()["nats"]
    rejected = nats_status["demand_rejected"]
    assert len(nats_status["gateways"]) == MAX_GATEWAYS
    assert rejected == {"too_many_gateways": n_fake - MAX_GATEWAYS, "malformed": 4, "oversized": 1, "out_of_range": 1}
    assert len(status.content) < 16_000, f"/v1/status is {len(status.content)} bytes"
    assert f'touchreal_nats_demand_rejected_total{{reason="too_many_gateways"}} {float(n_fake - MAX_GATEWAYS)}' in metrics
    assert demand == {"SA1": (0,)}  # what the admitted gateways asked for, nothing more


def test_deploy_nats_wires_the_config_credentials_and_ports_the_commands_have():
    """No container engine runs here: the compose file and the manifests pass the broker the config
    this file's tests run, and the services only environment variables and flags they really read."""
    import argparse

    import yaml

    from touchreal.bridge import command as gateway_command
    from touchreal.bridge.gateway import GatewaySettings
    from touchreal.commands import serve as serve_command

    deploy = CONF.parent
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    serve_command.register(sub)
    gateway_command.register(sub)
    known_env = {f"TOUCHREAL_NATS_{name.upper()}" for name in NatsAuth.model_fields} | {"TOUCHREAL_TOKEN"}
    port = GatewaySettings().port
    compose = yaml.safe_load((deploy / "compose.yaml").read_text())["services"]
    assert "-c" in compose["nats"]["command"] and compose["nats"]["volumes"] == [f"./{CONF.name}:/etc/nats/{CONF.name}:ro"]
    assert set(compose["nats"]["environment"]) == {"TOUCHREAL_NATS_PUBLISHER_PASSWORD", "TOUCHREAL_NATS_GATEWAY_PASSWORD"}
    assert all(f"${k}" in CONF.read_text() for k in compose["nats"]["environment"])
    for name, svc in compose.items():
        if name == "nats":
            continue
        args = parser.parse_args(svc["command"])
        assert set(svc["environment"]) <= known_env and svc["environment"]["TOUCHREAL_NATS_USER"] in ("publisher", "gateway")
        if svc["command"][0] == "gateway":
            assert svc["ports"][0].endswith(f":{port}") and str(port) in svc["healthcheck"]["test"][-1]
            assert args.sensor_id == "lab-1"
    docs = {d["metadata"]["name"] + "/" + d["kind"]: d for f in (deploy / "k8s").glob("*.yaml")
            for d in yaml.safe_load_all(f.read_text())}
    (gw,) = docs["gateway-lab-1/Deployment"]["spec"]["template"]["spec"]["containers"]
    parser.parse_args(gw["args"])
    assert gw["ports"][0]["containerPort"] == port and {e["name"] for e in gw["env"]} <= known_env
    (nats_c,) = docs["nats/Deployment"]["spec"]["template"]["spec"]["containers"]
    assert nats_c["args"][:2] == ["-c", f"/etc/nats/{CONF.name}"]


def test_grasp_force_example_runs_through_a_gateway(tmp_path, broker):
    """clients/examples/grasp_force.py against a gateway: the decoder routes are the publisher's,
    asked over the authenticated broker; the model it downloads decodes the gateway's spikes exactly
    as the service's own decoder does (--check)."""
    pytest.importorskip("onnxruntime")
    example = Path(__file__).resolve().parents[1] / "clients" / "examples" / "grasp_force.py"
    url, pub_auth, gw_auth = broker
    with publishing(tmp_path, url, publisher={"auth": pub_auth}) as (addr, svc, pub), \
            gateway(url, auth=gw_auth) as (ga, gw):
        listed = httpx.get(f"http://{ga}/v1/decoders").json()
        one = httpx.get(f"http://{ga}/v1/decoders/force")
        missing = httpx.get(f"http://{ga}/v1/decoders/nope/model.onnx")
        onnx = httpx.get(f"http://{ga}/v1/decoders/force/model.onnx")
        direct = httpx.get(f"http://{addr}/v1/decoders/force/model.onnx")
        run_ = subprocess.run([sys.executable, example, "--url", f"http://{ga}", "--seconds", "5", "--check"],
                              capture_output=True, text=True, timeout=120)
    assert listed == json.loads(json.dumps(svc.decoders_view())) and one.json()["name"] == "force"
    assert missing.status_code == 404 and "nope" in missing.json()["detail"]
    assert onnx.status_code == 200 and onnx.content == direct.content and len(onnx.content) > 1000
    assert run_.returncode == 0, run_.stderr
    assert len(run_.stdout.splitlines()) > 60 and "max |local - service| = 0 N" in run_.stderr


def test_gateway_decoder_routes_say_503_without_a_publisher(broker):
    url, _, gw_auth = broker
    gw = Gateway(GatewaySettings(nats=url, sensor_id="nobody", host="127.0.0.1", port=0), gw_auth)
    with serving_app(create_gateway_app(gw)) as ga:
        wait_until(lambda: gw.nc is not None and gw.nc.is_connected, 10, "the gateway connected to NATS")
        listed = httpx.get(f"http://{ga}/v1/decoders", timeout=30)
        onnx = httpx.get(f"http://{ga}/v1/decoders/force/model.onnx", timeout=30)
    assert listed.status_code == onnx.status_code == 503 and "did not answer" in listed.json()["detail"]


def test_publisher_and_gateway_over_tls(tmp_path):
    """The shipped permissions behind TLS: a self-signed certificate for 127.0.0.1, the clients verify
    it with --nats-tls-ca; a client that does not speak TLS gets nowhere."""
    import shutil

    if not natsd.available() or shutil.which("openssl") is None:
        pytest.skip("needs nats-server and openssl (Debian: apt-get install nats-server openssl)")
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                    "-keyout", tmp_path / "key.pem", "-out", tmp_path / "cert.pem", "-days", "1", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True)
    shutil.copy(CONF, tmp_path / CONF.name)
    conf = tmp_path / "tls.conf"
    conf.write_text(f'tls {{cert_file: "{tmp_path / "cert.pem"}", key_file: "{tmp_path / "key.pem"}"}}\n'
                    f'include "{CONF.name}"\n')
    env = {"TOUCHREAL_NATS_PUBLISHER_PASSWORD": "p" * 16, "TOUCHREAL_NATS_GATEWAY_PASSWORD": "g" * 16}
    ca = tmp_path / "cert.pem"
    with natsd.local_nats_server(config=conf, env=env) as plain_url:
        url = plain_url.replace("nats://", "tls://")
        pub_auth = NatsAuth(user="publisher", password="p" * 16, tls_ca=ca)
        with publishing(tmp_path / "state", url, publisher={"auth": pub_auth}) as (_, svc, _p), \
                gateway(url, auth=NatsAuth(user="gateway", password="g" * 16, tls_ca=ca)) as (ga, gw):

            async def go():
                async with connect(ga) as ws:
                    hello, _ = await hello_and_subscribe(ws)
                    frames = await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 10)
                with pytest.raises((NatsError, OSError)):  # no TLS: refused
                    await nats.connect(plain_url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False,
                                       user="gateway", password="g" * 16)
                return hello, frames

            hello, frames = run(go())
    assert hello["session"] == svc.session and n_spikes(frames) >= 10
    assert gw.status()["auth"] == "user gateway over TLS"
