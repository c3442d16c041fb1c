"""Browser-facing hardening, against real uvicorn servers on 127.0.0.1 and real httpx:

* every HTTP response of the service and of a gateway carries the security headers
  (Content-Security-Policy, X-Content-Type-Options, X-Frame-Options, Referrer-Policy), the strict
  policy everywhere but on /docs; errors (400, 401, 404, 422, 500) included;
* the middleware leaves WebSockets and streamed bodies alone;
* /docs references no other host, and every file it names is served by the app itself;
* in headless Chromium with no network, /docs renders Swagger UI and runs a request under its
  CSP, and the browser logs no CSP violation (while an injected inline script is refused).
"""

from __future__ import annotations

import asyncio
import json
import re
import threading
from collections.abc import Iterator
from html.parser import HTMLParser
from types import SimpleNamespace
from urllib.parse import urljoin, urlsplit

import httpx
import pytest
from fastapi import FastAPI
from fastapi.responses import StreamingResponse
from server_harness import connect, free_port, running_server, wait_until
from test_dashboard import browser, csp_violations, in_page  # noqa: F401  (browser: the Chromium fixture)

from touchreal.bridge.gateway import Gateway, create_gateway_app
from touchreal.bridge.settings import GatewaySettings
from touchreal.server.app import serving_app
from touchreal.server.browser import SecurityHeaders, server_error
from touchreal.server.settings import ServeSettings

STRICT_DIRECTIVES = {"default-src", "object-src", "base-uri", "form-action", "frame-ancestors"}


def directives(csp: str) -> dict[str, list[str]]:
    """A Content-Security-Policy header as {directive: [sources]}."""
    parsed = {}
    for part in filter(None, (p.strip() for p in csp.split(";"))):
        name, *sources = part.split()
        parsed[name] = sources
    return parsed


def assert_secure(response: httpx.Response, docs_page: bool = False) -> None:
    """The security headers: the strict CSP (on the docs page: plus style attributes and data:
    images, never inline or eval'd scripts), nosniff, no framing, no referrer."""
    what = f"{response.request.method} {response.request.url.path} -> {response.status_code}"
    h = response.headers
    assert h.get("x-content-type-options") == "nosniff", what
    assert h.get("x-frame-options") == "DENY", what
    assert h.get("referrer-policy") == "no-referrer", what
    assert h.get_list("content-security-policy") == [h.get("content-security-policy")], what  # one policy
    csp = directives(h.get("content-security-policy", ""))
    assert csp.get("default-src") == ["'self'"] and csp.get("frame-ancestors") == ["'none'"], what
    assert csp.get("object-src") == ["'none'"] and csp.get("base-uri") == ["'none'"], what
    assert "script-src" not in csp and "connect-src" not in csp, what  # default-src 'self' governs both
    if docs_page:
        assert set(csp) == STRICT_DIRECTIVES | {"style-src-attr", "img-src"}, what
        assert csp["style-src-attr"] == ["'unsafe-inline'"] and csp["img-src"] == ["'self'", "data:"], what
    else:
        assert set(csp) == STRICT_DIRECTIVES, what


class Page(HTMLParser):
    """What an HTML page loads (src/href values) and whether it has inline script of any kind."""

    def __init__(self, text: str):
        super().__init__()
        self.urls: list[str] = []
        self.inline: list[str] = []
        self.data_openapi_url: str | None = None
        self._in_script = False
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self.urls += [v for k, v in attrs if k in ("src", "href") and v]
        self.inline += [f"{tag} {k}" for k, _ in attrs if k.startswith("on")]
        self._in_script = tag == "script"
        if tag == "script" and not a.get("src"):
            self.inline.append("script without src")
        self.data_openapi_url = a.get("data-openapi-url", self.data_openapi_url)

    def handle_endtag(self, tag: str) -> None:
        self._in_script = False

    def handle_data(self, data: str) -> None:
        if self._in_script and data.strip():
            self.inline.append("script text")


def get_pages(http: httpx.Client) -> list[httpx.Response]:
    """A GET of every parameterless GET route the app's OpenAPI document lists (whatever it answers)."""
    paths = http.get("/openapi.json").json()["paths"]
    return [http.get(p) for p, ops in paths.items() if "get" in ops and "{" not in p]


def check_docs_offline(http: httpx.Client) -> None:
    """/docs names no other host, has no inline script, and each file it loads is served 200 here."""
    page = http.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert_secure(page, docs_page=True)
    assert not re.search(r"(https?:)?//", page.text), "the docs page names another host"
    parsed = Page(page.text)
    assert parsed.inline == []
    assert len(parsed.urls) == 4  # icon, stylesheet, Swagger UI, our init
    for url in [*parsed.urls, parsed.data_openapi_url]:
        assert not urlsplit(url).scheme and not urlsplit(url).netloc, url
        asset = http.get(urljoin(str(page.url), url))
        assert asset.status_code == 200 and asset.content, url
        assert_secure(asset)
        if url.endswith(".css"):  # what the stylesheet loads in turn: only data: images
            assert all(u.strip("'\"").startswith("data:") for u in re.findall(r"url\(([^)]*)\)", asset.text))
    assert http.get(urljoin(str(page.url), parsed.data_openapi_url)).json() == http.get("/openapi.json").json()


@pytest.fixture
def gateway_addr() -> Iterator[str]:
    """A gateway app on a free loopback port; its NATS URL is a closed loopback port (no broker is
    needed for its pages)."""
    gw = Gateway(GatewaySettings(nats=f"nats://127.0.0.1:{free_port()}", sensor_id="s1"))
    with serving_app(create_gateway_app(gw)) as addr:
        yield addr


async def _hello(addr: str) -> dict:
    async with connect(addr) as ws:
        return json.loads(await asyncio.wait_for(ws.recv(), 10))


def test_every_service_response_carries_the_security_headers(tmp_path):
    with running_server(tmp_path, token="tok") as (addr, _), \
            httpx.Client(base_url=f"http://{addr}", timeout=10) as http:
        pages = get_pages(http)
        assert {r.request.url.path for r in pages} >= {"/v1/health", "/v1/status", "/v1/config", "/metrics"}
        responses = [
            *(http.get(p) for p in ("/", "/index.html", "/dashboard.js", "/protocol.js", "/style.css",
                                    "/favicon.svg", "/openapi.json", "/v1/health", "/metrics")),
            http.head("/"),
            http.get("/v1/nothing"), http.get("/nothing.js"), http.get("/redoc"),  # 404s: /redoc is off
            http.get("/", headers={"Host": "attacker.example"}),  # 400: not an allowed host
            http.patch("/v1/config", json={"window_ms": 64}),  # 401: no token
            http.patch("/v1/config", json={"window_ms": "x"}, headers={"Authorization": "Bearer tok"}),  # 422
        ]
        assert [r.status_code for r in responses[-6:]] == [404, 404, 404, 400, 401, 422]
        assert all(r.status_code == 200 for r in responses[:-6])
        for r in [*pages, *responses]:
            assert_secure(r)
        check_docs_offline(http)
        assert asyncio.run(_hello(addr))["type"] == "hello"  # the WebSocket passes the middleware untouched


def test_every_gateway_response_carries_the_security_headers_and_its_docs_are_offline(gateway_addr):
    with httpx.Client(base_url=f"http://{gateway_addr}", timeout=10) as http:
        pages = get_pages(http)
        assert {r.request.url.path for r in pages} >= {"/v1/health", "/v1/ready", "/metrics"}
        for r in [*pages, http.get("/openapi.json"), http.get("/nothing"), http.get("/redoc")]:
            assert_secure(r)
        check_docs_offline(http)
        assert asyncio.run(_hello(gateway_addr))["type"] == "hello"


def test_headers_on_an_unhandled_error_and_a_streamed_body_is_not_held_back():
    """The 500 of an exception carries the headers (and says the connection closes); a streamed
    body's first chunk reaches the client while the app still holds back the second (the middleware
    buffers nothing)."""
    release = threading.Event()
    app = FastAPI()
    app.state.service = SimpleNamespace(settings=ServeSettings.model_construct())  # serving_app's keepalive pings
    app.add_exception_handler(Exception, server_error)
    app.add_middleware(SecurityHeaders)

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("a bug")

    @app.get("/stream")
    def stream() -> StreamingResponse:
        async def chunks():
            yield b"first;"
            await asyncio.to_thread(release.wait, 10)
            yield b"second"
        return StreamingResponse(chunks(), media_type="text/plain")

    with serving_app(app) as addr, httpx.Client(base_url=f"http://{addr}", timeout=10) as http:
        boom = http.get("/boom")
        assert boom.status_code == 500 and boom.text == "Internal Server Error"
        assert boom.headers["connection"] == "close"  # uvicorn closes it after an exception
        assert_secure(boom)
        with http.stream("GET", "/stream") as r:
            assert_secure(r)
            chunks = r.iter_raw()
            assert next(chunks) == b"first;"  # before release: times out (10 s) if it was buffered
            release.set()
            assert b"".join(chunks) == b"second"


def browser_log_where(driver, predicate, seconds: float = 10.0) -> list[dict]:
    """Browser log entries, gathered (``wait_until`` polls the log) until ``predicate(entries)`` holds."""
    entries: list[dict] = []

    def gathered() -> bool:
        entries.extend(driver.get_log("browser"))
        return predicate(entries)

    wait_until(gathered, seconds, lambda: f"the browser log to show it; browser log: {entries}", interval=0.1)
    return entries


@pytest.fixture(params=["service", "gateway"])
def app_addr(request, tmp_path) -> Iterator[str]:
    """The address of a service, or of a gateway."""
    if request.param == "service":
        with running_server(tmp_path) as (addr, _):
            yield addr
    else:
        yield request.getfixturevalue("gateway_addr")


def test_docs_render_offline_in_chromium_under_the_csp(browser, app_addr):  # noqa: F811  (browser: a fixture)
    from selenium.webdriver.common.by import By

    browser.get(f"http://{app_addr}/docs")
    path = "[data-path='/v1/health']"
    in_page(browser, f"return document.querySelector(\"#swagger-ui .opblock-summary-path{path}\")")
    # run GET /v1/health from the page: Try it out, Execute, the answer shown (connect-src 'self')
    browser.find_element(By.CSS_SELECTOR, f".opblock-summary-path{path}").click()
    in_page(browser, "return document.querySelector('.opblock.is-open .try-out__btn')").click()
    in_page(browser, "return document.querySelector('.opblock.is-open .execute')").click()
    status = in_page(browser, "const c = document.querySelector('.opblock.is-open .live-responses-table "
                               "tr.response .response-col_status'); return c && c.textContent.trim()")
    assert status == "200"
    entries = browser.get_log("browser")
    assert csp_violations(entries) == [] and [e for e in entries if e["level"] == "SEVERE"] == []

    # the policy is enforced, and a violation would be in the log: an injected inline script is refused
    browser.execute_script("const s = document.createElement('script'); s.textContent = 'window.inlineRan = 1';"
                           "document.body.append(s)")
    assert browser.execute_script("return window.inlineRan") is None
    assert csp_violations(browser_log_where(browser, csp_violations))
