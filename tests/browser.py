"""Shared helpers of the browser tests (Playwright with Debian's Chromium): the browser fixture,
logging in, axe-core accessibility checks and the layout checks of the console bars."""

from __future__ import annotations

import os
import time
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


def watch(page) -> None:
    """Record on ``page`` its uncaught errors (``page.errors``) and requests (``page.requests``:
    (wall time, method, url))."""
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(f"{e}\n{getattr(e, 'stack', '')}"))
    page.requests = []
    page.on("request", lambda r: page.requests.append((time.time(), r.method, r.url)))


def take_errors(page) -> list[str]:
    """The page errors recorded since the last call (see :func:`watch`), and forget them."""
    errors, page.errors[:] = list(page.errors), []
    return errors


def press(page, selector: str) -> None:
    """Click a page button without Playwright's "stable for two animation frames" wait (the
    WebGL iframe starves animation frames on a loaded machine); the button's handler runs as on a
    real click. Clicks in the 3D view use the real mouse."""
    page.locator(selector).wait_for()
    page.locator(selector).dispatch_event("click")


def set_target(page, x: float, y: float) -> None:
    """Type the target (x, y), m, into the console's fields and press Set; returns once the server
    has answered it (the page's target set, nothing typed or being edited) and the target line
    shows it."""
    page.fill("#target-x", str(x))
    page.fill("#target-y", str(y))
    press(page, "#target-set")
    page.wait_for_function("() => !state.typed && !state.editing && state.target")
    page.locator("#target", has_text="from the turn axis").wait_for()


def put_machine_at(up, machine_id: str, q_active) -> None:
    """Move the simulated machine of the `slinger up` stack ``up`` to ``q_active`` (4,) (SimReset,
    what a tool may send under the server's certificate)."""
    from runtime.protocol import keys
    from runtime.protocol.messages import SimReset, encode
    from runtime.zenoh_session import TlsFiles, open_session

    hub = f"tls/127.0.0.1:{up.argv[up.argv.index('--zenoh-port') + 1]}"
    with open_session(mode="peer", connect=(hub,), listen=("tls/127.0.0.1:0",),
                      tls=TlsFiles.from_site(up.data_dir / "site", "server")) as session:
        time.sleep(1.0)  # the peers' gossip links us to the plant
        for _ in range(3):
            session.put(keys.sim_reset(machine_id), encode(SimReset(machine_id=machine_id, stamp_s=time.monotonic(),
                                                                    q_active=list(q_active))))
            time.sleep(0.3)


def open_console(browser, base_url: str, viewport=(1440, 900), timeout_ms: int = 180_000, machine: str = "m1 READY"):
    """A new browser context with the admin's console page (watched: :func:`watch`) showing
    ``machine`` in its state badge: returns (context, page); the caller closes the context."""
    ctx = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
    page = ctx.new_page()
    page.set_default_timeout(timeout_ms)
    watch(page)
    log_in(page, base_url)
    page.locator("#machine-state", has_text=machine).wait_for()
    return ctx, page


@pytest.fixture(autouse=False)
def no_page_errors(request):
    """After each test of a module that imports this fixture: no uncaught error in its console
    page (the module's ``ann`` fixture)."""
    yield
    if "ann" in request.fixturenames:
        errors = take_errors(request.getfixturevalue("ann"))
        assert errors == [], errors


def stack_pid(up, role: str, machine_id: str) -> int:
    """The pid of the `slinger <role>` process (plant, runtime) of ``machine_id`` in the
    `slinger up` stack ``up`` (its own --machine-id: the id of every machine also stands in a
    runtime's --acl-machines list)."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if (cmd[1:4] == [b"-m", b"server.cli", role.encode()] and b"--machine-id" in cmd
                    and cmd[cmd.index(b"--machine-id") + 1] == machine_id.encode()
                    and any(str(up.data_dir).encode() in c for c in cmd)):
                return int(entry.name)
    pytest.fail(f"no {role} process of {machine_id}")
