"""deploy/: no container engine runs here, so test what can be tested.

* The Dockerfile, compose file and Kubernetes manifests parse and name the ports, paths, settings
  and command-line flags the service really has.
* The image's entrypoint command (ENTRYPOINT + CMD + ENV of deploy/Dockerfile), run in a fresh
  virtual environment with only the two wheels installed (dependencies from the pip cache), serves
  the dashboard and the REST API, passes the image's HEALTHCHECK command and streams spikes (after
  the image's build-time numba warm-up step, run the same way).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml
from server_harness import free_port, wait_until
from touchreal_client import Client

from touchreal.commands import serve as command
from touchreal.server.app import create_app
from touchreal.server.service import Service
from touchreal.server.settings import RuntimeConfig, ServeSettings

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"


def dockerfile() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of deploy/Dockerfile, continuation lines joined, comments dropped."""
    out, cur = [], ""
    for line in (DEPLOY / "Dockerfile").read_text().splitlines():
        if not cur and (not line.strip() or line.lstrip().startswith("#")):
            continue
        cur += line.rstrip("\\").strip() + " "
        if not line.endswith("\\"):
            word, _, rest = cur.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
            cur = ""
    return out


def image_env() -> dict[str, str]:
    env = {}
    for word, rest in dockerfile():
        if word == "ENV":
            env.update(kv.split("=", 1) for kv in shlex.split(rest))
    return env


def exec_form(word: str) -> list[str]:
    return json.loads([rest for w, rest in dockerfile() if w == word][-1])


def serve_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    command.register(parser.add_subparsers(dest="cmd"))
    return parser


def setting_names() -> set[str]:
    return {f"TOUCHREAL_{name.upper()}" for name in ServeSettings.model_fields}


def routes(tmp_path) -> set[str]:
    """The HTTP paths the service really serves (its OpenAPI document)."""
    app = create_app(Service(ServeSettings(state_dir=tmp_path / "state"), RuntimeConfig()))
    return set(app.openapi()["paths"])


def test_dockerfile_is_multi_stage_non_root_with_healthcheck_volumes_and_a_valid_command(tmp_path):
    steps = dockerfile()
    assert sum(w == "FROM" for w, _ in steps) == 2 and "from=wheels" in " ".join(r for w, r in steps if w == "RUN")
    user = [r for w, r in steps if w == "USER"][-1]
    assert user not in ("root", "0")
    env = image_env()
    assert {k for k in env if k.startswith("TOUCHREAL_")} <= setting_names()
    port = int(env["TOUCHREAL_PORT"])
    assert [r for w, r in steps if w == "EXPOSE"] == [str(port)]
    state = env["TOUCHREAL_STATE_DIR"]
    svc = Service(ServeSettings(state_dir=tmp_path / "state"), RuntimeConfig())  # where the service looks for models
    models = Path(state) / svc.models.user_dir.relative_to(tmp_path / "state")
    assert json.loads([r for w, r in steps if w == "VOLUME"][0]) == [state, str(models)]
    health = [r for w, r in steps if w == "HEALTHCHECK"][0]
    assert "/v1/health" in health and "/v1/health" in routes(tmp_path)
    entry, cmd = exec_form("ENTRYPOINT"), exec_form("CMD")
    assert entry == ["touchreal", "serve"]
    args = serve_parser().parse_args(entry[1:] + cmd)
    assert command.settings_from(args).source == "sim" and args.func is command.run
    for w, rest in steps:  # everything COPYed from the context exists and is let through .dockerignore
        if w == "COPY" and "--from" not in rest:
            for src in shlex.split(rest)[:-1]:
                assert (ROOT / src).exists(), src
    ignore = (DEPLOY / "Dockerfile.dockerignore").read_text()
    assert all(f"!{p}" in ignore for p in ("clients/python", "service", "pyproject.toml", "README.md"))


def test_compose_and_kubernetes_manifests_reference_the_real_ports_paths_settings_and_flags(tmp_path):
    env, known = image_env(), routes(tmp_path)
    port = int(env["TOUCHREAL_PORT"])
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    svc = compose["services"]["touchreal"]
    assert (DEPLOY / svc["build"]["context"] / svc["build"]["dockerfile"]).resolve() == DEPLOY / "Dockerfile"
    assert svc["ports"] == [f"127.0.0.1:{port}:{port}"]
    assert {v.split(":")[1] for v in svc["volumes"]} == {env["TOUCHREAL_STATE_DIR"], env["TOUCHREAL_STATE_DIR"] + "/models"}
    assert serve_parser().parse_args(["serve", *svc["command"]]).source == "sim"
    assert set(svc["environment"]) <= setting_names()
    serial = [ln.lstrip("# ") for ln in (DEPLOY / "compose.yaml").read_text().splitlines() if "serial:/dev/" in ln]
    assert serial and "devices" in (DEPLOY / "compose.yaml").read_text()  # the commented hardware variant

    kust = yaml.safe_load((DEPLOY / "k8s" / "kustomization.yaml").read_text())
    docs = {}
    for name in kust["resources"]:
        for doc in yaml.safe_load_all((DEPLOY / "k8s" / name).read_text()):
            docs[doc["kind"]] = doc
    assert set(docs) == {"ConfigMap", "PersistentVolumeClaim", "Deployment", "Service"}
    cm, dep, service = docs["ConfigMap"]["data"], docs["Deployment"], docs["Service"]
    pod = dep["spec"]["template"]["spec"]
    (c,) = pod["containers"]
    assert c["livenessProbe"]["httpGet"]["path"] == "/v1/health" and c["readinessProbe"]["httpGet"]["path"] == "/v1/ready"
    assert {"/v1/health", "/v1/ready", "/metrics"} <= known
    assert dep["spec"]["template"]["metadata"]["annotations"]["prometheus.io/path"] == "/metrics"
    (cport,) = c["ports"]
    assert cport["containerPort"] == port and c["livenessProbe"]["httpGet"]["port"] == cport["name"]
    assert service["spec"]["ports"][0]["targetPort"] == cport["name"]
    assert service["spec"]["selector"] == dep["spec"]["selector"]["matchLabels"] == dep["spec"]["template"]["metadata"]["labels"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    # no args: the ConfigMap's and the Deployment's variables are valid settings of `touchreal serve`
    assert "args" not in c
    settings_env = set(cm) | {e["name"] for e in c["env"]}
    assert settings_env <= setting_names()
    settings = ServeSettings(**{k.removeprefix("TOUCHREAL_").lower(): v for k, v in cm.items()})
    assert settings.source == "sim" and "localhost" in settings.allowed_hosts
    for probe in ("livenessProbe", "readinessProbe", "startupProbe"):
        assert {"name": "Host", "value": "localhost"} in c[probe]["httpGet"]["httpHeaders"]
    env_values = {e["name"]: e["value"] for e in c["env"]}
    mounts = {m["mountPath"] for m in c["volumeMounts"]}
    assert {env_values["TOUCHREAL_STATE_DIR"]} == mounts
    assert env_values["TOUCHREAL_STATE_DIR"] == env["TOUCHREAL_STATE_DIR"] and int(env_values["TOUCHREAL_PORT"]) == port
    claim = pod["volumes"][0]["persistentVolumeClaim"]["claimName"]
    assert claim == docs["PersistentVolumeClaim"]["metadata"]["name"]


@pytest.mark.slow  # ~100 s: out of the default suite; .ci/run runs it (pytest -m slow)
def test_image_entrypoint_serves_and_streams_from_a_fresh_venv_with_only_the_wheels(tmp_path):
    """~60 s: the wheels build without index access for our own code; dependencies come from the
    pip cache (--no-compile keeps it bounded); the venv is deleted afterwards."""
    wheels, venv = tmp_path / "wheels", tmp_path / "venv"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    try:
        subprocess.run([*pip, "wheel", "--no-deps", "-w", wheels, ROOT / "clients" / "python", ROOT],
                       check=True, capture_output=True, timeout=300)
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True, timeout=120)
        py = venv / "bin" / "python"
        subprocess.run([*pip, "--python", py, "install", "--no-compile", *sorted(wheels.glob("*.whl"))],
                       check=True, capture_output=True, timeout=600)
        where = subprocess.run([py, "-c", "import touchreal, touchreal_client; print(touchreal.__file__, touchreal_client.__file__)"],
                               check=True, capture_output=True, text=True, cwd=tmp_path, timeout=120).stdout.split()
        assert all(Path(w).is_relative_to(venv) for w in where), where  # not the source tree

        port = free_port()
        env = {**{k: v for k, v in os.environ.items() if not k.startswith("TOUCHREAL_")}, **image_env()}
        env.update(TOUCHREAL_HOST="127.0.0.1", TOUCHREAL_PORT=str(port),  # loopback only in tests
                   TOUCHREAL_STATE_DIR=str(tmp_path / "state"),
                   NUMBA_CACHE_DIR=str(tmp_path / "numba"))
        # the image compiles the numba kernels at build time: run that step the same way
        (warm,) = [r for w, r in dockerfile() if w == "RUN" and "prove_runnable" in r]
        warm_cmd = shlex.split(warm.split("&&")[0])
        assert warm_cmd[0] == "python"
        subprocess.run([py, *warm_cmd[1:]], env=env, cwd=tmp_path, check=True, timeout=600)
        entry = exec_form("ENTRYPOINT")
        proc = subprocess.Popen([venv / "bin" / entry[0], *entry[1:], *exec_form("CMD")], env=env, cwd=tmp_path,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            with Client(f"http://127.0.0.1:{port}") as tr:
                def up() -> bool:
                    assert proc.poll() is None, "the entrypoint exited"
                    try:
                        tr.wait_ready(5)
                    except Exception:
                        return False
                    return True

                wait_until(up, 120, "the entrypoint came up")
                page = httpx.get(f"http://127.0.0.1:{port}/", timeout=10)
                hc = [r for w, r in dockerfile() if w == "HEALTHCHECK"][0]
                hc_cmd = json.loads(hc[hc.index("CMD") + 3:].strip())
                hc_run = subprocess.run([venv / "bin" / hc_cmd[0], *hc_cmd[1:]], env=env, timeout=30)
                with tr.stream() as s:
                    frames = []  # frames come every 5 ms hop: read until spikes came (the scene's first touch)
                    for f in s.spikes():
                        frames.append(f)
                        if sum(x.t_us.size for x in frames) >= 10 or len(frames) >= 2000:
                            break
                    session = s.hello["session"]
                assert tr.health()["session"] == session
        finally:
            proc.terminate()
            out = proc.communicate(timeout=30)[0]
        assert hc_run.returncode == 0
        assert page.status_code == 200 and '<canvas id="raster"' in page.text
        assert sum(f.t_us.size for f in frames) >= 10
        assert f"dashboard http://127.0.0.1:{port}/" in out
    finally:
        shutil.rmtree(venv, ignore_errors=True)
        shutil.rmtree(wheels, ignore_errors=True)
