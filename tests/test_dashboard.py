"""The live dashboard (static files served at /) in a real headless Chromium driven by Selenium,
against a real service on 127.0.0.1 with the simulated source.

Needs Debian's chromium and chromium-driver (/usr/bin/chromium, /usr/bin/chromedriver; `.ci/run`
installs them); skips with that reason where they are missing. The browser resolves no host name
(only 127.0.0.1 is reached), so a page that needs the internet fails here. The page runs under the
service's Content-Security-Policy: a violation is an error in the browser log and fails the test.
Set TOUCHREAL_DASHBOARD_SCREENSHOT to a path to keep the screenshot (docs/img/dashboard.png is
made that way).

tests/test_server_browser.py reuses :func:`browser`, :func:`in_page` and :func:`csp_violations`.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import httpx
import pytest
from server_harness import running_server, wait_until

from touchreal.server.settings import RuntimeConfig

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


def test_dashboard_is_served_without_shadowing_the_api(tmp_path):
    with running_server(tmp_path) as (addr, _):
        with httpx.Client(base_url=f"http://{addr}", timeout=10) as http:
            page = http.get("/")
            js = http.get("/dashboard.js")
            assert page.status_code == 200 and "text/html" in page.headers["content-type"]
            assert '<canvas id="raster"' in page.text and js.status_code == 200
            assert all(http.get(f).status_code == 200 for f in ("/protocol.js", "/style.css", "/favicon.svg"))
            assert http.get("/v1/health").json()["status"] == "ok"
            assert http.get("/openapi.json").json()["info"]["title"] == "TouchReal"
            assert "swagger" in http.get("/docs").text.lower()
            assert "touchreal_" in http.get("/metrics").text
            assert http.get("/v1/nothing").status_code == 404 and http.get("/nothing.js").status_code == 404


@pytest.fixture
def browser(tmp_path):
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip("no browser: install Debian's chromium and chromium-driver "
                    "(apt-get install chromium chromium-driver) to run the dashboard test")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (test extra) is not installed")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1280,1000", f"--user-data-dir={tmp_path / 'chromium'}",
                 "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"):  # no network: no name resolves
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    driver.set_page_load_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()


def in_page(driver, script: str, seconds: float = 30.0):
    """The first truthy value of ``script`` in the page (``wait_until`` polls it every 0.2 s); a failure
    shows the dashboard's message list (if the page has one) and the browser log."""

    def awaited() -> str:
        page_log = driver.execute_script("const log = document.getElementById('log'); return log && log.innerText")
        return f"{script}\npage log:\n{page_log}\nbrowser log:\n{driver.get_log('browser')}"

    return wait_until(lambda: driver.execute_script(script), seconds, awaited, interval=0.2)


def csp_violations(entries: list[dict]) -> list[dict]:
    """The Content-Security-Policy violations among browser log entries (Chromium logs each one,
    with source 'security')."""
    return [e for e in entries if e.get("source") == "security" or "Content Security Policy" in e["message"]]


@pytest.mark.slow
def test_dashboard_draws_live_spikes_and_drives_subscription_and_window(browser, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    with running_server(tmp_path / "state", RuntimeConfig(taxels=3), token="tok") as (addr, svc):
        browser.get(f"http://{addr}/")
        in_page(browser, "return window.touchreal && window.touchreal.connected")
        # spikes drawn on the raster, the force trace filled from the channels stream
        in_page(browser, "const s = window.touchreal; return s.drawnSpikes > 20 && s.frames > 60 && s.force.size === 3")
        # the decoded force (the shipped force model, run by the service) is drawn and shown in N
        in_page(browser, "return window.touchreal.decodedForce.size > 0 && "
                          "document.getElementById('decoded-force').textContent.includes(' N (force')")
        shot = tmp_path / "dashboard.png"
        frames = browser.execute_script("return window.touchreal.frames")  # a little more history on the canvases
        in_page(browser, f"return window.touchreal.frames > {frames + 150}")
        browser.save_screenshot(str(shot))
        stats = browser.execute_script("const s = window.touchreal; return [s.events, s.gaps, s.hello.session, "
                                       "document.getElementById('delivery').textContent]")
        assert stats[0] > 20 and stats[1] == 0 and stats[2] == svc.session and stats[3].endswith("ms")
        # latency per class from the clock model: the page maps with the service's own line
        in_page(browser, "return window.touchreal.spikeLatency.SA1.length > 10")
        line, lat_sa1, shown = browser.execute_script(
            "const s = window.touchreal, c = s.clocks[s.clocks.length - 1], a = [...s.spikeLatency.SA1].sort((x, y) => x - y);"
            "return [c.wall_us - c.sensor_us, a[a.length >> 1], document.getElementById('latency').textContent]")
        assert line == svc.clock.wall_us - svc.clock.sensor_us
        assert 0 < lat_sa1 < 150_000 and shown.endswith("ms") and shown.split(" / ")[0].isdigit(), (lat_sa1, shown)

        # subscription control: PC spikes of taxels 1 and 2, no decoders -> exactly that is computed.
        # The form is driven from the keyboard (space toggles a box, Enter submits the form through its
        # subscribe button): a mouse click lands on coordinates, which the live readouts above can shift.
        for name, value in (("cls", "SA1"), ("cls", "RA"), ("stream", "decoded")):
            box = browser.find_element(By.CSS_SELECTOR, f"input[name={name}][value={value}]")
            box.send_keys(Keys.SPACE)
            assert not box.is_selected(), (name, value)
        taxels = browser.find_element(By.ID, "taxels")
        taxels.clear()
        taxels.send_keys("1,2", Keys.ENTER)
        in_page(browser, "const s = window.touchreal.subscribed; return s && s.classes.join() === 'PC'")
        wait_until(lambda: dict(svc.hub.demand.columns) == {"PC": (1, 2)}, 10,
                   lambda: f"PC of taxels 1 and 2 demanded: {dict(svc.hub.demand.columns)}")

        # causal window: refused without the token (logged, nothing changes), applied with it
        def apply_window(ms: str) -> None:
            win = browser.find_element(By.ID, "window-ms")
            win.clear()
            win.send_keys(ms, Keys.ENTER)  # submits through the apply button

        apply_window("64")
        in_page(browser, "return document.getElementById('log').textContent.includes('HTTP 401')")
        assert svc.view.config_view()["window_ms"] == 128
        browser.find_element(By.ID, "token").send_keys("tok")
        apply_window("64")
        in_page(browser, "return document.getElementById('config').textContent.includes('window 64 ms')")
        assert svc.view.config_view()["window_ms"] == 64

        entries = browser.get_log("browser")
    assert csp_violations(entries) == []
    assert [e for e in entries if e["level"] == "SEVERE" and "401" not in e["message"]] == []
    assert shot.stat().st_size > 10_000
    if os.environ.get("TOUCHREAL_DASHBOARD_SCREENSHOT"):
        shutil.copyfile(shot, os.environ["TOUCHREAL_DASHBOARD_SCREENSHOT"])


def test_dashboard_draws_a_populations_afferent_spikes(browser, tmp_path):
    plan = tmp_path / "plan.json"
    plan.write_text('{"variants": {"SA1": [1.0], "RA": [1.0], "PC": [1.0]}}')
    with running_server(tmp_path / "state", RuntimeConfig(taxels=4), population=str(plan)) as (addr, svc):
        browser.get(f"http://{addr}/")
        in_page(browser, "return window.touchreal && window.touchreal.connected")
        # subscribed with protocol version 2 to spikes only (a population has no channels), and spikes drawn
        in_page(browser, "const s = window.touchreal.subscribed; return s && s.streams.join() === 'spikes'")
        in_page(browser, "return window.touchreal.drawnSpikes > 20")
        conn = browser.execute_script("return document.getElementById('conn').textContent")
        entries = browser.get_log("browser")
    assert "940 afferents over 4 taxel(s)" in conn
    assert [e for e in entries if e["level"] == "SEVERE"] == []
