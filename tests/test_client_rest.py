"""touchreal_client's REST helpers against a real service on 127.0.0.1 (sync and async)."""

from __future__ import annotations

import asyncio
import json

import pytest
from server_harness import free_port, running_server
from touchreal_client import AsyncClient, AuthError, Client, NotFound, ParamsRejected, ServiceUnavailable


def test_config_token_params_upload_history_and_rollback(tmp_path):
    with running_server(tmp_path / "state", token="s3cret") as (addr, svc):
        with Client(f"http://{addr}") as anon, Client(f"http://{addr}", token="s3cret") as tr:
            assert tr.health()["session"] == svc.session
            assert tr.config()["window_ms"] == 128.0
            with pytest.raises(AuthError, match="Bearer"):
                anon.patch_config(window_ms=64)
            changed = tr.patch_config(window_ms=64)
            assert changed["config"]["window_ms"] == 64 and "pipeline" in changed["restarted"]
            active = tr.params()
            assert active["params"]["preprocess"]["window_ms"] == 64 and active["rev"] == 2

            bad = json.loads(json.dumps(active["params"]))
            bad["preprocess"]["update_ms"] = "fast"
            bad["preprocess"]["mains_hz"] = None
            with pytest.raises(ParamsRejected) as rejected:
                tr.put_params(bad)
            fields = [loc for loc, _ in rejected.value.errors]
            assert "preprocess.update_ms" in fields and "preprocess.mains_hz" in fields
            assert tr.params()["rev"] == 2  # the old set stays

            good = tmp_path / "p.json"
            active["params"]["preprocess"]["window_ms"] = 96.0
            good.write_text(json.dumps(active["params"]))
            assert tr.put_params(good)["rev"] == 3
            with pytest.raises(ValueError, match="not valid JSON"):
                (tmp_path / "broken.json").write_text("{")
                tr.put_params(tmp_path / "broken.json")
            assert [r["rev"] for r in tr.params_history()["revisions"]] == [1, 2, 3]
            with pytest.raises(NotFound):
                tr.rollback(99)
            assert tr.rollback(1)["rev"] == 4 and tr.config()["window_ms"] == 128.0
            assert "touchreal_" in tr.metrics()


def test_async_rest_waits_for_readiness_and_names_an_unreachable_service(tmp_path):
    with running_server(tmp_path) as (addr, _):

        async def go():
            async with AsyncClient(f"http://{addr}") as tr:
                await tr.wait_ready(30)
                return await tr.ready(), await tr.status()

        (ok, reason), status = asyncio.run(go())
    assert ok and reason == "ok" and status["source"]["spec"] == "sim"

    async def unreachable():
        async with AsyncClient(f"http://127.0.0.1:{free_port()}", timeout_s=2) as tr:
            with pytest.raises(ServiceUnavailable, match="/v1/config"):
                await tr.config()
            with pytest.raises(ServiceUnavailable, match="not ready after"):
                await tr.wait_ready(0.3)

    asyncio.run(unreachable())
