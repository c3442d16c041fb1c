"""The guards in front of the routes (server/security.py) against hostile input, on a real server:
body checks linear in the body that never hold the event loop, throttled and visible authentication
failures, and serial sources that cannot open refused with the previous source restored."""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import pty
import random
import threading
import time

import httpx
import pytest
from server_harness import connect, hello_and_subscribe, running_server, wait_until

from touchreal.server.security import MAX_JSON_DEPTH, MAX_NUMBER_CHARS, AuthThrottle, JsonShape, token_ok

MiB = 1 << 20


def _reference_shape(text: bytes) -> tuple[int, int]:
    """(deepest nesting, longest number literal) by a plain byte-by-byte reading: strings skipped with
    their escapes; a backslash run outside a string escapes a quote as one inside would."""
    depth = deepest = run = longest = 0
    in_string = escaped = False
    for ch in text.decode("latin-1"):
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
            continue
        if ch == '"' and not escaped:
            in_string, run = True, 0
            continue
        escaped = ch == "\\" and not escaped
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
        run = run + 1 if ch in "0123456789+-.eE" else 0
        longest = max(longest, run)
    return deepest, longest


def test_json_shape_fed_in_any_slices_agrees_with_a_plain_reading():
    rng = random.Random(7)
    alphabet = b'[]{}"\\\\1e.-a ,:'
    for _ in range(3000):
        text = bytes(rng.choice(alphabet) for _ in range(rng.randint(0, 60)))
        shape, i = JsonShape(), 0
        while i < len(text):
            k = rng.randint(1, 7)
            shape.feed(text[i:i + k])
            i += k
        shape.feed(b"", final=True)
        assert (shape.max_depth, shape.max_number) == _reference_shape(text), text


def test_json_shape_names_each_problem():
    def problem(text: bytes) -> str | None:
        shape = JsonShape()
        shape.feed(text, final=True)
        return shape.problem()

    assert problem(b'{"a": [1, {"b": "]]]\\"[[["}]}') is None
    assert "deeper" in problem(b"[" * (MAX_JSON_DEPTH + 1))
    assert problem(b'"' + b"[" * 10_000 + b'"') is None  # brackets inside a string do not nest
    assert "number" in problem(b"1" * (MAX_NUMBER_CHARS + 1))
    assert "UTF-8" in problem(b'{"a": "\xff"}')
    assert "UTF-8" in problem(b'{"a": "\xe2\x82')  # cut in the middle of a character


def test_the_token_comparison_accepts_only_the_bearer_token():
    assert token_ok(None, None) and token_ok("s3cret", "Bearer s3cret") and token_ok("s3cret", "bearer  s3cret ")
    for given in (None, "", "Bearer", "Bearer s3cre", "Bearer s3cret!", "Basic s3cret", "Bearer " + "x" * 100_000):
        assert not token_ok("s3cret", given)


def _adversarial(shape: str, n: int) -> bytes:
    """A body of about ``n`` bytes of one hostile shape."""
    return {
        "escaped quotes": b'"' + b'\\"' * (n // 2),  # an unterminated string of escapes: quadratic for a regex
        "escapes": b'"' + b"\\\\" * (n // 2),
        "quotes": b"[" + b'"\\"",' * (n // 5) + b"1]",
        "long string": b'{"rev": "' + b"x" * n + b'"}',
        "deep nesting": b"[" * n,
        "huge number": b'{"rev": ' + b"9" * n + b"}",
        "invalid UTF-8": b'{"rev": "' + b"\xc3\x28" * (n // 2) + b'"}',
    }[shape]


def test_hostile_bodies_take_time_linear_in_their_size_while_a_subscriber_streams(tmp_path):
    """Each hostile shape, doubled from 128 KiB up to the 1 MiB limit: refused with 4xx, the handling
    time (client-side round trip, the best of five) at most about doubles with each doubling, and a subscriber's frames keep coming at the hop rate
    (no gap near the old freeze: 18 s for 48 KB)."""
    gaps: list[float] = []
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}", timeout=60) as http:
        stop = threading.Event()

        def subscriber() -> None:
            async def go():
                async with connect(addr) as ws:
                    await hello_and_subscribe(ws, classes=["SA1"])
                    last = time.monotonic()
                    while not stop.is_set():
                        msg = await asyncio.wait_for(ws.recv(), 10)
                        if isinstance(msg, bytes):
                            now = time.monotonic()
                            gaps.append(now - last)
                            last = now

            asyncio.run(go())

        reader = threading.Thread(target=subscriber, daemon=True)
        reader.start()
        wait_until(lambda: len(gaps) >= 50, 30, "the subscriber's first frames")
        times: dict[str, list[float]] = {}
        for shape in ("escaped quotes", "escapes", "quotes", "long string", "deep nesting", "huge number", "invalid UTF-8"):
            for n in (128 << 10, 256 << 10, 512 << 10, MiB - 64):
                body = _adversarial(shape, n)[: MiB]
                best = float("inf")
                for _ in range(5):  # the best of five: the machine's other work only ever adds time
                    t0 = time.perf_counter()
                    r = http.put("/v1/params", content=body, headers={"Content-Type": "application/json"})
                    best = min(best, time.perf_counter() - t0)
                    assert r.status_code in (400, 422), (shape, n, r.status_code, r.text[:200])
                times.setdefault(shape, []).append(best)
        during = len(gaps)
        wait_until(lambda: len(gaps) >= during + 20, 30, "frames after the bodies")
        stop.set()
        reader.join(15)
    for shape, t in times.items():
        # linear: 8x the size about 8x the time, where quadratic is 64x. The bounds leave room for a
        # loaded machine's noise (at most 8^1.5 overall, 4x a step) and still fail a quadratic check
        ms = [round(x * 1000, 1) for x in t]
        assert all(large <= 4 * small + 0.020 for small, large in zip(t, t[1:])), (shape, ms)
        assert t[-1] <= 8 ** 1.5 * t[0] + 0.020 and t[-1] < 1.0, (shape, ms)
    assert max(gaps[50:]) < 0.25, max(gaps[50:])  # the stream never stalled


def test_failed_authentication_is_throttled_per_peer_logged_and_counted(tmp_path, caplog):
    """A guesser at 127.0.0.2 gets 401 six times (five free failures, then the one that earns a block), then 429 with Retry-After, even with the right token
    (no oracle while blocked) and whatever X-Forwarded-For it claims; the client at 127.0.0.1 with the
    token is never refused; each failure is a warning and a metric."""
    caplog.set_level(logging.WARNING, logger="touchreal.server")
    with running_server(tmp_path, token="s3cret") as (addr, svc), \
            httpx.Client(base_url=f"http://{addr}", transport=httpx.HTTPTransport(local_address="127.0.0.2")) as guesser, \
            httpx.Client(base_url=f"http://{addr}", headers={"Authorization": "Bearer s3cret"}) as owner:
        rollback = {"rev": 1}
        codes = [guesser.post("/v1/params/rollback", json=rollback, headers={"Authorization": f"Bearer guess{i}"})
                 for i in range(12)]
        assert [r.status_code for r in codes] == [401] * 6 + [429] * 6  # the sixth failure earns the first block
        assert int(codes[6].headers["Retry-After"]) >= 1
        spoofed = guesser.post("/v1/params/rollback", json=rollback,
                               headers={"Authorization": "Bearer s3cret", "X-Forwarded-For": "203.0.113.9"})
        assert spoofed.status_code == 429  # blocked: not even the right token is looked at
        for _ in range(3):  # the owner, from another address, is never affected
            assert owner.patch("/v1/config", json={"classes": ["SA1", "RA", "PC"]}).status_code == 200
        metrics = httpx.get(f"http://{addr}/metrics").text
        failures = svc.metrics.auth.labels("failure")._value.get()
        throttled = svc.metrics.auth.labels("throttled")._value.get()
        assert failures == 6 and throttled == 7
        assert 'touchreal_auth_refused_total{outcome="failure"} 6.0' in metrics
        wait_until(lambda: guesser.post("/v1/params/rollback", json=rollback,
                                        headers={"Authorization": "Bearer s3cret"}).status_code != 429,
                   30, "the guesser's back-off to end")
    warnings = [r.getMessage() for r in caplog.records if "failed authentication from 127.0.0.2" in r.getMessage()]
    assert len(warnings) == 6 and "refused for" in warnings[-1]
    assert all("s3cret" not in r.getMessage() and "guess" not in r.getMessage() for r in caplog.records)


def test_the_throttle_backs_off_exponentially_forgets_and_stays_bounded():
    now = [0.0]
    throttle = AuthThrottle(free=2, base_s=1.0, max_s=8.0, forget_s=100.0, max_peers=3, clock=lambda: now[0])
    assert [throttle.failed("a") for _ in range(7)] == [0, 0, 1, 2, 4, 8, 8]
    assert throttle.retry_after("a") == 8 and throttle.retry_after("b") == 0
    now[0] += 200.0  # quiet for longer than forget_s: a fresh start
    assert throttle.failed("a") == 0
    throttle.succeeded("a")
    assert throttle.retry_after("a") == 0
    for peer in "bcde":
        throttle.failed(peer)
    assert len(throttle._peers) == 3 and "b" not in throttle._peers  # the quietest went first


@pytest.fixture
def pty_device():
    master, slave = pty.openpty()
    try:
        yield os.ttyname(slave)
    finally:
        os.close(slave)
        os.close(master)


def test_a_serial_source_that_cannot_open_is_refused_and_the_previous_source_runs(tmp_path, pty_device):
    with running_server(tmp_path) as (addr, svc), httpx.Client(base_url=f"http://{addr}", timeout=30) as http:
        held = os.open(pty_device, os.O_RDWR | os.O_NOCTTY)
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another program has the device (as pyserial does)
        try:
            for spec, why in (("serial:/dev/null", "not a serial device"), ("serial:/dev/ttyTR-absent", "not found"),
                              (f"serial:{pty_device}", "busy")):
                r = http.patch("/v1/config", json={"source": spec})
                assert r.status_code == 409, (spec, r.status_code, r.text)
                detail = r.json()["detail"]
                assert why in detail and "the previous source 'sim' runs again" in detail, detail
                assert http.get("/v1/config").json()["source"] == "sim"
                wait_until(lambda: http.get("/v1/ready").status_code == 200, 30, "the simulated e-skin to stream again")
        finally:
            os.close(held)
        r = http.patch("/v1/config", json={"source": f"serial:{pty_device}"})  # now free: accepted
        assert r.status_code == 200 and r.json()["config"]["source"] == f"serial:{pty_device}"
        wait_until(lambda: http.get("/v1/status").json()["source"].get("port") == pty_device, 10, "the serial source")
