"""NATS with authentication: a real nats-server started with the shipped deploy/nats/nats-server.conf
(the publisher's password user, an nkey user per gateway identity, subject permissions), the
service's publisher and gateways authenticating to it; and no secret shown anywhere."""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import logging
import secrets
import subprocess
import sys
from collections.abc import Iterator
from contextlib import AsyncExitStack
from dataclasses import dataclass
from pathlib import Path

import httpx
import nats
import numpy as np
import pytest
from nats.errors import Error as NatsError
from server_harness import collect, connect, hello_and_subscribe, n_spikes, needs_nats_server, until, wait_until
from test_bridge_nats import SENSOR, gateway, publishing
from touchreal_client import protocol as P

from touchreal.commands import gateway as gateway_command
from touchreal.bridge import natsd, subjects
from touchreal.bridge.auth import NatsAuth
from touchreal.bridge.credentials import issue, permissions_entry
from touchreal.bridge.demand import MAX_ANNOUNCEMENT_BYTES, MAX_GATEWAYS, Announced, announcement
from touchreal.bridge.gateway import Gateway, create_gateway_app
from touchreal.bridge.settings import GatewaySettings
from touchreal.server.app import serving_app
from touchreal.server.settings import RuntimeConfig

CONF = Path(__file__).resolve().parents[1] / "deploy" / "nats" / "nats-server.conf"
GATEWAYS = ("gateway-1", "gateway-2")  #: the gateway identities the shipped config admits


@dataclass
class Broker:
    url: str
    publisher: NatsAuth
    gateways: dict[str, NatsAuth]  #: gateway id -> its own nkey credentials


def _shipped_env(keys: Path) -> tuple[dict[str, str], NatsAuth, dict[str, NatsAuth]]:
    """The environment the shipped config reads (a fresh publisher password, the public keys of newly
    issued gateway nkeys in ``keys``), and the publisher's and each gateway's credentials."""
    password = "tr_" + secrets.token_hex(16)
    env = {"TOUCHREAL_NATS_PUBLISHER_PASSWORD": password}
    gateways = {}
    for gid in GATEWAYS:
        seed, public = issue(gid, keys)
        env[f"TOUCHREAL_NATS_{gid.upper().replace('-', '_')}_NKEY"] = public
        gateways[gid] = NatsAuth(nkey=seed)
    return env, NatsAuth(user="publisher", password=password), gateways


def _conf_with(tmp_path: Path, users: list[str]) -> Path:
    """The shipped config with more entries in its users list (as an operator adds a gateway)."""
    conf = tmp_path / "nats.conf"
    conf.write_text(CONF.read_text().replace("  users = [\n", "  users = [\n" + "".join(f"    {u}\n" for u in users), 1))
    return conf


@pytest.fixture
def broker(tmp_path) -> Iterator[Broker]:
    """A nats-server running the shipped config, with the credentials of the publisher and both gateways."""
    needs_nats_server()
    env, publisher, gateways = _shipped_env(tmp_path / "nkeys")
    with natsd.local_nats_server(config=CONF, env=env) as url:
        yield Broker(url, publisher, gateways)


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


def _spikes(frames: list) -> list:
    return [f for f in frames if isinstance(f, P.SpikesFrame)]


def _served_without_pause(frames: list) -> bool:
    """Consecutive ``seq``, nothing dropped, and SA1's watermark moving on in steps under 0.5 s: the
    publisher never stopped publishing for this client (a withdrawn demand stops it for a second or more)."""
    seqs = [f.header.seq for f in frames]
    finals = np.array([f.final_us["SA1"] for f in frames])
    return (len(frames) > 20 and seqs == list(range(seqs[0], seqs[0] + len(seqs))) and frames[-1].header.dropped == 0
            and np.diff(finals).max() <= 500_000)


def test_authenticated_publisher_and_gateway_stream_and_nobody_else_gets_in(tmp_path, broker):
    with publishing(tmp_path, broker.url, RuntimeConfig(taxels=2), publisher={"auth": broker.publisher}) as (addr, svc, pub), \
            gateway(broker.url, auth=broker.gateways["gateway-1"], gateway_id="gateway-1") as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                hello, _ = await hello_and_subscribe(ws, taxels=[1])
                frames = await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 30, what="30 spikes frames")
            with pytest.raises((NatsError, OSError)):  # no credentials: the broker refuses the connection
                await nats.connect(broker.url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False)
            wrong = NatsAuth(user="publisher", password="not-the-password")
            with pytest.raises((NatsError, OSError)):
                await nats.connect(broker.url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False,
                                   **wrong.connect_options())
            fake = announcement("gateway-1", Announced({c: [0, 1] for c in P.CLASSES}))
            gw_auth, url = broker.gateways["gateway-1"], broker.url
            refused = [await _refused_publish(url, broker.publisher, subjects.demand(SENSOR, "gateway-1"), fake),
                       await _refused_publish(url, gw_auth, subjects.frames(SENSOR), b"TR"),  # gateways: no frames
                       await _refused_publish(url, gw_auth, subjects.hello(SENSOR), b"{}")]  # nor hello announcements
            return hello, frames, refused

        hello, frames, refused = run(go())
        status = httpx.get(f"http://{addr}/v1/status").json()["nats"]
    spikes = _spikes(frames)
    assert hello["session"] == svc.session and len(spikes) >= 30
    seqs = [f.header.seq for f in spikes]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and all(set(f.taxel.tolist()) <= {1} for f in spikes)
    for error, subject in zip(refused, (subjects.demand(SENSOR, "gateway-1"), subjects.frames(SENSOR),
                                        subjects.hello(SENSOR))):
        assert subject in error.lower(), error  # each refusal names the subject it refused
    assert status["auth"] == "user publisher" and status["demand_rejected"]["identity_mismatch"] == 0
    assert gw.status()["auth"] == f"nkey {broker.gateways['gateway-1'].nkey}"


def test_a_gateway_cannot_silence_another(tmp_path, broker):
    """Gateway-1's credentials against gateway-2, whose id anyone can read on its /v1/health: the broker
    refuses gateway-1's publishes on gateway-2's demand subject, and empty demand naming gateway-2 that
    gateway-1 publishes on its own subject (up to 200/s, 400 times) is dropped and counted by the
    publisher. Gateway-2's client is served throughout."""
    g1 = broker.gateways["gateway-1"]
    with publishing(tmp_path, broker.url, RuntimeConfig(taxels=2), publisher={"auth": broker.publisher}) as (_, _, pub), \
            gateway(broker.url, auth=broker.gateways["gateway-2"], gateway_id="gateway-2") as (gb, _):
        mismatched = lambda: pub.status()["demand_rejected"]["identity_mismatch"]  # noqa: E731
        victim = httpx.get(f"http://{gb}/v1/health").json()["gateway"]

        async def go():
            silence = announcement(victim, Announced({}))
            attacker = await nats.connect(broker.url, **g1.connect_options())

            async def flood():  # up to 200 announcements a second, for as long as the client collects
                while True:
                    await attacker.publish(subjects.demand(SENSOR, "gateway-1"), silence)
                    await asyncio.sleep(1 / 200)  # the flood's pace, not a wait

            async with connect(gb) as ws:
                await hello_and_subscribe(ws)
                await until(lambda: pub.demand.gateways == [victim], 10, "gateway-2's demand reached the publisher")
                refused = await _refused_publish(broker.url, g1, subjects.demand(SENSOR, victim), silence)
                flooding = asyncio.create_task(flood())
                try:
                    frames = await collect(ws, 30.0, lambda fs: mismatched() >= 400,
                                           what="400 fake withdrawals dropped")
                    live = pub.demand.gateways
                finally:
                    flooding.cancel()
                    await attacker.close()
            return refused, _spikes(frames), live

        refused, frames, live = run(go())
    assert victim == "gateway-2" and subjects.demand(SENSOR, "gateway-2") in refused.lower()
    assert mismatched() >= 400 and live == ["gateway-2"]  # every fake withdrawal dropped; gateway-1 holds no place
    assert _served_without_pause(frames)


def test_one_identity_holds_one_place_and_a_restarted_gateway_gets_its_own_back(tmp_path, broker):
    """Two places (max_gateways=2). Gateway-1's credentials flood: demand under its own id, announcements
    naming other ids in the body, publishes on other ids' subjects. It holds one place. Gateway-2 crashed
    and left its last announcement live (published here with its credentials, a 60 s TTL), so both places
    are taken when it comes back under its id: it renews its own and its client's demand is served."""
    g1, g2 = broker.gateways["gateway-1"], broker.gateways["gateway-2"]
    with publishing(tmp_path, broker.url, RuntimeConfig(taxels=4),
                    publisher={"auth": broker.publisher, "max_gateways": 2}) as (_, _, pub):
        rejected = lambda: pub.status()["demand_rejected"]  # noqa: E731

        async def go():
            refusals: list[str] = []

            async def on_error(exc):
                refusals.append(str(exc))

            flooder = await nats.connect(broker.url, error_cb=on_error, **g1.connect_options())

            async def flood():
                for i in itertools.count():
                    body = announcement("gateway-1" if i % 2 else f"fake{i}", Announced({"SA1": [0]}), ttl_s=60.0)
                    await flooder.publish(subjects.demand(SENSOR, "gateway-1"), body)
                    await flooder.publish(subjects.demand(SENSOR, f"fake{i}"), body)  # the broker drops these
                    await asyncio.sleep(1 / 200)  # the flood's pace (200 a second), not a wait

            flooding = asyncio.create_task(flood())
            try:
                await until(lambda: pub.demand.gateways == ["gateway-1"], 20, "the publisher hears gateway-1")
                crashed = await nats.connect(broker.url, **g2.connect_options())
                await crashed.publish(subjects.demand(SENSOR, "gateway-2"),
                                      announcement("gateway-2", Announced({"RA": [0]}), ttl_s=60.0))
                await crashed.drain()
                await until(lambda: pub.demand.gateways == ["gateway-1", "gateway-2"]
                            and rejected()["identity_mismatch"] >= 100, 20, "both places taken while gateway-1 floods")
                async with AsyncExitStack() as stack:
                    gb, _ = await asyncio.to_thread(stack.enter_context,
                                                    gateway(broker.url, auth=g2, gateway_id="gateway-2"))
                    async with connect(gb) as ws:
                        await hello_and_subscribe(ws, taxels=[3], classes=["PC"])
                        frames = _spikes(await collect(ws, 20.0, lambda fs: n_spikes(fs) >= 30, what="30 spikes frames"))
                        lane, live = pub.lanes[subjects.frames(SENSOR)].subscription, pub.demand.gateways
            finally:
                flooding.cancel()
                await flooder.close()
            return frames, lane, live, refusals

        frames, lane, live, refusals = run(go())
        counts = rejected()
    assert live == ["gateway-1", "gateway-2"] and counts["too_many_gateways"] == 0 and counts["identity_mismatch"] >= 100
    assert len(refusals) >= 100 and all("permissions violation" in r for r in refusals)  # other ids' subjects
    assert 3 in lane.taxels and "PC" in lane.classes and "RA" not in lane.classes  # the renewal replaced the leftover
    assert len(frames) >= 30 and all(set(f.taxel.tolist()) <= {3} and set(f.cls.tolist()) <= {2} for f in frames)


def test_issued_credentials_admit_a_new_gateway_under_its_id(tmp_path, capsys):
    """`touchreal gateway credentials --id gateway-3 --out DIR`: its printed entry, added to the shipped
    config, lets a gateway with that seed and id serve; its seed file is the owner's alone."""
    needs_nats_server()
    parser = argparse.ArgumentParser()
    gateway_command.register(parser.add_subparsers())
    args = parser.parse_args(["gateway", "credentials", "--id", "gateway-3", "--out", str(tmp_path / "keys")])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    (entry,) = [line.strip() for line in printed.splitlines() if line.strip().startswith("{nkey:")]
    seed = tmp_path / "keys" / "gateway-3.nk"
    assert (seed.stat().st_mode & 0o777) == 0o600 and seed.read_text().strip() not in printed
    with pytest.raises(FileExistsError):  # an issued seed is never overwritten
        args.func(args)
    env, publisher, _ = _shipped_env(tmp_path / "nkeys")
    with natsd.local_nats_server(config=_conf_with(tmp_path, [entry]), env=env) as url, \
            publishing(tmp_path / "state", url, publisher={"auth": publisher}) as (_, svc, pub), \
            gateway(url, auth=NatsAuth(nkey=seed), gateway_id="gateway-3") as (ga, gw):

        async def go():
            async with connect(ga) as ws:
                hello, _ = await hello_and_subscribe(ws)
                return hello, await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 10, what="10 spikes frames"), \
                    pub.demand.gateways

        hello, frames, live = run(go())
    assert hello["session"] == svc.session and n_spikes(frames) >= 10 and live == ["gateway-3"]
    assert f"--gateway-id gateway-3 --nats-nkey {seed}" in printed


@pytest.mark.slow  # ~21 s of announcement floods; .ci/run runs it (pytest -m slow)
def test_demand_announcements_are_bounded_dropped_and_counted(tmp_path, nats_url):  # noqa: F811
    """On a broker that lets anyone announce under any id (plain nats-server, no config): 100k fake
    gateway ids, each on its own subject, plus oversized, malformed, out-of-range and mismatched
    announcements. The publisher keeps at most MAX_GATEWAYS, counts every drop, and /v1/status stays small."""
    n_fake = 100_000
    with publishing(tmp_path, nats_url, RuntimeConfig(taxels=4)) as (addr, svc, pub):

        async def go():
            nc = await nats.connect(nats_url)
            one = Announced({"SA1": [0]})
            for i in range(n_fake):
                await nc.publish(subjects.demand(SENSOR, f"fake{i}"), announcement(f"fake{i}", one, ttl_s=30.0))
            subject = subjects.demand(SENSOR, "x")
            await nc.publish(subject, b"{" * 200 + b"}" * 200)
            await nc.publish(subject, b'{"gateway": "x", "ttl_ms": NaN, "columns": {}}')
            await nc.publish(subject, json.dumps({"gateway": "g.x", "ttl_ms": 1000, "columns": {}}).encode())
            await nc.publish(subject, json.dumps({"gateway": "x", "ttl_ms": 1000, "columns": {},
                                                  "channels": [0] * (MAX_ANNOUNCEMENT_BYTES // 2)}).encode())
            await nc.publish(subject, announcement("x", Announced({"PC": [4]})))
            await nc.publish(subject, announcement("x", one, ttl_s=3600.0))
            await nc.publish(subject, announcement("fake0", Announced({})))  # x withdrawing fake0's demand
            await nc.flush()
            await nc.close()
            seen = lambda: sum(pub.status()["demand_rejected"].values()) + len(pub.demand.gateways)  # noqa: E731
            await until(lambda: seen() >= n_fake + 7, 60, "every announcement handled")

        run(go(), 120)
        status = httpx.get(f"http://{addr}/v1/status")
        metrics = httpx.get(f"http://{addr}/metrics").text
        demand = dict(svc.hub.demand.columns)
    nats_status = status.json()["nats"]
    rejected = nats_status["demand_rejected"]
    assert len(nats_status["gateways"]) == MAX_GATEWAYS and "fake0" in nats_status["gateways"]
    assert rejected == {"too_many_gateways": n_fake - MAX_GATEWAYS, "malformed": 4, "oversized": 1, "out_of_range": 1,
                        "identity_mismatch": 1}
    assert len(status.content) < 16_000, f"/v1/status is {len(status.content)} bytes"
    assert f'touchreal_nats_demand_rejected_total{{reason="too_many_gateways"}} {float(n_fake - MAX_GATEWAYS)}' in metrics
    assert demand == {"SA1": (0,)}  # what the admitted gateways asked for, nothing more


def test_deploy_nats_gives_each_gateway_its_own_identity_and_wires_what_the_commands_read():
    """No container engine runs here: the compose file and the manifests pass the broker the config
    this file's tests run with the variables it reads, give each gateway an id the config admits and
    that id's seed, and pass the services only environment variables and flags they really read."""
    import yaml

    from touchreal.commands import serve as serve_command

    deploy, conf = CONF.parent, CONF.read_text()
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    serve_command.register(sub)
    gateway_command.register(sub)
    known_env = ({f"TOUCHREAL_NATS_{name.upper()}" for name in NatsAuth.model_fields} | {"TOUCHREAL_TOKEN"}
                 | {f"TOUCHREAL_GATEWAY_{name.upper()}" for name in GatewaySettings.model_fields})
    port = GatewaySettings().port
    admitted = [gid for gid in GATEWAYS if f"permissions: {permissions_entry(gid)}" in conf]
    assert admitted == list(GATEWAYS) and conf.count("touchreal.*.demand.") == len(GATEWAYS) + 1  # + the publisher's

    top = yaml.safe_load((deploy / "compose.yaml").read_text())
    compose = top["services"]
    assert "-c" in compose["nats"]["command"] and compose["nats"]["volumes"] == [f"./{CONF.name}:/etc/nats/{CONF.name}:ro"]
    assert set(compose["nats"]["environment"]) == {"TOUCHREAL_NATS_PUBLISHER_PASSWORD", "TOUCHREAL_NATS_GATEWAY_1_NKEY",
                                                   "TOUCHREAL_NATS_GATEWAY_2_NKEY"}
    assert all(f"${k}" in conf for k in compose["nats"]["environment"])
    ids = []
    for name, svc in compose.items():
        if name == "nats":
            continue
        args = parser.parse_args(svc["command"])
        assert set(svc["environment"]) <= known_env
        if svc["command"][0] == "gateway":
            ids.append(args.gateway_id)
            (secret,) = svc["secrets"]  # its own seed, where `credentials --out deploy/nats/secrets` writes it
            assert svc["environment"] == {"TOUCHREAL_NATS_NKEY": f"/run/secrets/{secret}"}
            assert top["secrets"][secret] == {"file": f"./secrets/{args.gateway_id}.nk"}
            assert svc["ports"][0].endswith(f":{port}") and str(port) in svc["healthcheck"]["test"][-1]
            assert args.sensor_id == "lab-1"
        else:
            assert svc["environment"]["TOUCHREAL_NATS_USER"] == "publisher"
    assert sorted(ids) == list(GATEWAYS)

    docs = {d["metadata"]["name"] + "/" + d["kind"]: d for f in (deploy / "k8s").glob("*.yaml")
            for d in yaml.safe_load_all(f.read_text())}
    sts = docs["gateway/StatefulSet"]["spec"]
    pods = [f"gateway-{sts['ordinals']['start'] + i}" for i in range(sts["replicas"])]
    assert pods == list(GATEWAYS)  # the pod names are the ids the config admits
    (gw,) = sts["template"]["spec"]["containers"]
    parser.parse_args(gw["args"])
    env = {e["name"]: e.get("value") for e in gw["env"]}
    assert gw["ports"][0]["containerPort"] == port and set(env) - {"POD_NAME"} <= known_env
    assert env["TOUCHREAL_GATEWAY_GATEWAY_ID"] == "$(POD_NAME)"
    (mount,) = gw["volumeMounts"]
    assert mount["mountPath"] == env["TOUCHREAL_NATS_NKEY"] and mount["subPathExpr"] == "$(POD_NAME).nk"
    (nats_c,) = docs["nats/Deployment"]["spec"]["template"]["spec"]["containers"]
    assert nats_c["args"][:2] == ["-c", f"/etc/nats/{CONF.name}"]
    assert {e["name"] for e in nats_c["env"]} == set(compose["nats"]["environment"])
    (sensor,) = docs["sensor-lab-1/Deployment"]["spec"]["template"]["spec"]["containers"]
    assert {e["name"] for e in sensor["env"]} <= known_env | {"TOUCHREAL_ALLOWED_HOSTS"}
    assert {"name": "TOUCHREAL_NATS_USER", "value": "publisher"} in sensor["env"]


@pytest.mark.slow
def test_grasp_force_example_runs_through_a_gateway(tmp_path, broker):
    """clients/examples/grasp_force.py against a gateway: the decoder routes are the publisher's,
    asked over the authenticated broker; the model it downloads decodes the gateway's spikes exactly
    as the service's own decoder does (--check)."""
    pytest.importorskip("onnxruntime")
    example = Path(__file__).resolve().parents[1] / "clients" / "examples" / "grasp_force.py"
    with publishing(tmp_path, broker.url, publisher={"auth": broker.publisher}) as (addr, svc, pub), \
            gateway(broker.url, auth=broker.gateways["gateway-1"], gateway_id="gateway-1") as (ga, gw):
        listed = httpx.get(f"http://{ga}/v1/decoders").json()
        one = httpx.get(f"http://{ga}/v1/decoders/force")
        missing = httpx.get(f"http://{ga}/v1/decoders/nope/model.onnx")
        onnx = httpx.get(f"http://{ga}/v1/decoders/force/model.onnx")
        direct = httpx.get(f"http://{addr}/v1/decoders/force/model.onnx")
        run_ = subprocess.run([sys.executable, example, "--url", f"http://{ga}", "--seconds", "5", "--check"],
                              capture_output=True, text=True, timeout=120)
    assert listed == json.loads(json.dumps(svc.view.decoders_view())) and one.json()["name"] == "force"
    assert missing.status_code == 404 and "nope" in missing.json()["detail"]
    assert onnx.status_code == 200 and onnx.content == direct.content and len(onnx.content) > 1000
    assert run_.returncode == 0, run_.stderr
    assert len(run_.stdout.splitlines()) > 60 and "max |local - service| = 0 N" in run_.stderr


def test_no_password_is_shown_anywhere(tmp_path, caplog):
    """The publisher and a gateway with their passwords in the URL (nats://USER:PASSWORD@...), a gateway
    of a sensor nobody publishes and one whose broker is away: neither password appears in /v1/status,
    /v1/health, /v1/ready, /metrics (service and gateways), the hellos, the error answers or any log
    record down to DEBUG; the URLs are shown masked and ``auth`` names the method."""
    needs_nats_server()
    caplog.set_level(logging.DEBUG)
    env, _, _ = _shipped_env(tmp_path / "nkeys")
    gw_password = "tr_" + secrets.token_hex(16)
    pub_password = env["TOUCHREAL_NATS_PUBLISHER_PASSWORD"]
    conf = _conf_with(tmp_path, [f'{{user: gateway-pw, password: "{gw_password}", '
                                 f'permissions: {permissions_entry("gateway-pw")}}}'])
    with natsd.local_nats_server(config=conf, env=env) as plain:
        pub_url, gw_url = (plain.replace("nats://", f"nats://{who}@") for who in
                           (f"publisher:{pub_password}", f"gateway-pw:{gw_password}"))
        dead_url = f"nats://gateway-pw:{gw_password}@127.0.0.1:{natsd.free_port()}"
        with publishing(tmp_path / "state", pub_url) as (addr, svc, pub), \
                gateway(gw_url, gateway_id="gateway-pw") as (ga, gw):

            async def hellos():
                async with connect(addr) as direct, connect(ga) as via:
                    (hd, _), (hv, _) = await hello_and_subscribe(direct), await hello_and_subscribe(via)
                    return [hd, hv], await collect(via, 10.0, lambda fs: n_spikes(fs) >= 10, what="10 spikes frames")

            (hd, hv), frames = run(hellos())
            shown = [httpx.get(f"http://{a}{path}").text for a in (addr, ga)
                     for path in ("/v1/status", "/v1/health", "/v1/ready", "/metrics")]
            statuses = httpx.get(f"http://{addr}/v1/status").json()["nats"], gw.status()
        errors = []
        for url, sensor in ((gw_url, "nobody"), (dead_url, SENSOR)):  # no publisher; no broker
            settings = GatewaySettings(nats=url, sensor_id=sensor, host="127.0.0.1", port=0, gateway_id="gateway-pw")
            lost = Gateway(settings)
            with serving_app(create_gateway_app(lost)) as la:
                if sensor == "nobody":
                    wait_until(lambda: lost.nc is not None and lost.nc.is_connected, 10, "the gateway connected")
                errors += [httpx.get(f"http://{la}{path}", timeout=30) for path in ("/v1/ready", "/v1/decoders",
                                                                                  "/v1/decoders/force/model.onnx")]
    masked = plain.replace("nats://", "nats://publisher:***@"), plain.replace("nats://", "nats://gateway-pw:***@")
    assert n_spikes(frames) >= 10  # the credentials in the URLs work
    assert statuses[0]["url"] == masked[0] and statuses[0]["auth"] == "user publisher (in the URL)"
    assert statuses[1]["nats"] == masked[1] and statuses[1]["auth"] == "user gateway-pw (in the URL)"
    assert all(r.status_code == 503 for r in errors) and "did not answer" in errors[1].json()["detail"]
    assert "not connected to NATS at nats://gateway-pw:***@127.0.0.1:" in errors[3].json()["reason"]
    assert f"publishing touchreal.{SENSOR}.frames to {masked[0]}" in caplog.text  # the URL is logged, masked
    texts = [*shown, json.dumps([hd, hv]), json.dumps(statuses), *(r.text for r in errors), caplog.text,
             *(r.getMessage() for r in caplog.records)]
    for password in (pub_password, gw_password):
        assert not [t for t in texts if password in t]


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
    env, publisher, gateways = _shipped_env(tmp_path / "nkeys")
    ca = tmp_path / "cert.pem"
    with natsd.local_nats_server(config=conf, env=env) as plain_url:
        url = plain_url.replace("nats://", "tls://")
        pub_auth = publisher.model_copy(update={"tls_ca": ca})
        gw_auth = gateways["gateway-1"].model_copy(update={"tls_ca": ca})
        with publishing(tmp_path / "state", url, publisher={"auth": pub_auth}) as (_, svc, _p), \
                gateway(url, auth=gw_auth, gateway_id="gateway-1") as (ga, gw):

            async def go():
                async with connect(ga) as ws:
                    hello, _ = await hello_and_subscribe(ws)
                    frames = await collect(ws, 10.0, lambda fs: n_spikes(fs) >= 10, what="10 spikes frames")
                with pytest.raises((NatsError, OSError)):  # no TLS: refused
                    await nats.connect(plain_url, max_reconnect_attempts=0, connect_timeout=2, allow_reconnect=False,
                                       user="publisher", password=env["TOUCHREAL_NATS_PUBLISHER_PASSWORD"])
                return hello, frames

            hello, frames = run(go())
    assert hello["session"] == svc.session and n_spikes(frames) >= 10
    assert gw.status()["auth"] == f"nkey {gateways['gateway-1'].nkey} over TLS"
