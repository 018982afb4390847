"""Shared helpers of the browser tests (Playwright with Debian's Chromium): the browser fixture,
logging in, axe-core accessibility checks and the layout checks of the console bars."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.conftest import ADMIN

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run"]
AXE_JS = Path(__file__).resolve().parent / "vendor" / "axe.min.js"
"""axe-core 4.11.0, the minified file of the npm package (MPL-2.0, tests/vendor/axe-core.LICENSE)."""
SIZES = [(1440, 900), (1024, 768), (390, 844)]
"""The three viewports of the console bars (desktop, small laptop, phone)."""


def _launch(p):
    if not os.path.exists(CHROMIUM):
        pytest.skip("Chromium is not installed (apt-get install -y chromium)")
    return p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, timeout=60_000)


def _chromium():
    """Headless Chromium for the length of a fixture (generator: yields the browser, closes it)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = _launch(p)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def browser():
    yield from _chromium()


@pytest.fixture(scope="module")
def module_browser():
    """One Chromium for a whole test module (the browser start is slow on 2 cores)."""
    yield from _chromium()


def log_in(page, base_url: str, user: tuple[str, str] = ADMIN, start: str = "/") -> None:
    """Open ``start``: the console sends us to the log-in page; log in there and come back."""
    page.goto(f"{base_url}{start}")
    page.wait_for_url("**/login.html**", timeout=30_000)
    page.fill("#username", user[0])
    page.fill("#password", user[1])
    page.click("#login")
    page.wait_for_url("**/console/**", timeout=30_000)
    page.locator("#who", has_text=user[0]).wait_for(timeout=30_000)


def axe_serious(page) -> list[str]:
    """Serious and critical axe-core violations of the page (the viser iframe excluded: it is a
    third-party WebGL canvas), as "rule: nodes" lines."""
    page.evaluate(AXE_JS.read_text())  # evaluated by the test harness: not subject to the page's CSP
    res = page.evaluate("""async () => {
        const r = await axe.run({ exclude: [["#viser"]] }, { resultTypes: ["violations"] });
        return r.violations.filter(v => ["serious", "critical"].includes(v.impact))
            .map(v => `${v.id} (${v.impact}): ${v.nodes.slice(0, 3).map(n => n.target.join(" ")).join(", ")}`);
    }""")
    return res


def layout(page) -> dict:
    """E-STOP box, viewport, document width and the 3D view's width on ``page``."""
    return page.evaluate("""() => {
        const r = (id) => { const e = document.getElementById(id); return e ? e.getBoundingClientRect().toJSON() : null; };
        return { estop: r("estop"), view: r("viser"), vw: innerWidth, vh: innerHeight,
                 scrollW: document.documentElement.scrollWidth };
    }""")
