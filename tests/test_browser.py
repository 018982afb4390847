"""The console in headless Chromium (Playwright): click the ground in the 3D view, press Throw,
see the throw in the history.

How the ground is clicked: with a REAL mouse click on viser's WebGL canvas inside the console's
iframe (``page.mouse.click`` at page pixels). Viser turns the click into a ray and the server
intersects it with z = 0 (server.scene.ground_point). The pixel for a wanted target is found by
calibration, not by assuming viser's camera conventions: three clicks near the view centre give
the local pixel -> ground map (a 2x2 Jacobian), Newton steps then aim at a point on the 2D
throwing plane until the clicked target lies within 10 cm of it. Reading the clicked target back
uses GET /api/scene (read-only); the throw itself is sent only by the page's Throw button.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.throw_geometry import ARM_PLANE_OFFSET_M, PLANE_TOLERANCE_M
from tests.conftest import ADMIN, SlingerUp, wait_for

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run"]


@pytest.fixture
def browser():
    import os

    if not os.path.exists(CHROMIUM):
        pytest.skip("Chromium is not installed (apt-get install -y chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, timeout=60_000)
        try:
            yield b
        finally:
            b.close()


def log_in(page, base_url: str, user: tuple[str, str] = ADMIN) -> None:
    """Open the console: it sends us to the log-in page; log in there and come back."""
    page.goto(f"{base_url}/")
    page.wait_for_url("**/login.html**", timeout=20_000)
    page.fill("#username", user[0])
    page.fill("#password", user[1])
    page.click("#login")
    page.wait_for_url("**/console/", timeout=20_000)
    page.locator("#who", has_text=user[0]).wait_for(timeout=20_000)


def _clicked_target(page, http, x: float, y: float, previous) -> np.ndarray:
    """Click the canvas at page pixel (x, y); return the new target the server computed."""
    page.mouse.click(x, y)

    def changed():
        t = http.get("/api/scene", timeout=2).json()["target"]
        return t if t is not None and t != previous else None

    return np.array(wait_for(changed, 10, f"a target from the click at ({x:.0f}, {y:.0f})"))


def click_ground_at(page, http, canvas_box: dict, want_xy, tol_m: float = 0.1) -> np.ndarray:
    """Click the 3D view so that the target lands within ``tol_m`` of ``want_xy`` (see module doc)."""
    px = np.array([canvas_box["x"] + 0.5 * canvas_box["width"], canvas_box["y"] + 0.6 * canvas_box["height"]])
    lo = np.array([canvas_box["x"] + 5, canvas_box["y"] + 5])
    hi = lo + np.array([canvas_box["width"], canvas_box["height"]]) - 10
    step = 30.0
    t0 = _clicked_target(page, http, *px, None)
    for _ in range(8):
        tx = _clicked_target(page, http, px[0] + step, px[1], t0.tolist())
        ty = _clicked_target(page, http, px[0], px[1] + step, tx.tolist())
        jac = np.column_stack([(tx - t0)[:2], (ty - t0)[:2]]) / step  # metres per pixel
        px = np.clip(px + np.linalg.solve(jac, np.asarray(want_xy) - t0[:2]), lo, hi)
        t0 = _clicked_target(page, http, *px, ty.tolist())
        if np.hypot(*(t0[:2] - want_xy)) < tol_m:
            return t0
    last = t0
    pytest.fail(f"could not click the ground near {want_xy}: last target {last}")


def test_click_ground_throw_and_see_it_in_history(tmp_path, browser):
    with SlingerUp(tmp_path) as up:
        machine = up.wait_machine_online()
        page = browser.new_page(viewport={"width": 1400, "height": 850})
        log_in(page, up.base_url)
        # the page says honestly that this is the simulated machine, and that it is online
        page.locator("#machine-kind", has_text="SIMULATED machine").wait_for(timeout=20_000)
        page.locator("#machine-online", has_text="online").wait_for(timeout=20_000)
        assert page.locator("#throw").is_disabled()  # no target yet

        canvas = page.frame_locator("#viser").locator("canvas").first
        canvas.wait_for(timeout=30_000)
        page.wait_for_timeout(2000)  # first frames rendered, click handler enabled
        box = canvas.bounding_box()
        assert box and box["width"] > 200 and box["height"] > 200

        yaw = machine["cabin_turn_rad"]  # the 2D plane follows the cabin
        r = 8.0
        want = np.array([r * math.cos(yaw) - ARM_PLANE_OFFSET_M * math.sin(yaw),
                         r * math.sin(yaw) + ARM_PLANE_OFFSET_M * math.cos(yaw)])
        target = click_ground_at(page, up.http, box, want)
        assert target[2] == 0.0 and np.hypot(*(target[:2] - want)) < PLANE_TOLERANCE_M

        # the page shows the clicked target and enables Throw
        page.locator("#target", has_text=f"x {target[0]:.2f}").wait_for(timeout=20_000)
        assert page.locator("#throw").is_disabled()  # not before a preview
        page.locator("#preview:not([disabled])").wait_for(timeout=20_000)
        page.click("#preview")
        page.locator("#pv-sigma", has_text="rollouts").wait_for(timeout=20_000)
        page.locator("#throw:not([disabled])").wait_for(timeout=20_000)
        page.click("#throw")
        page.locator("#status", has_text="accepted").wait_for(timeout=15_000)

        row = page.locator("#history tbody tr").first
        row.wait_for(timeout=15_000)
        page.locator("#history tbody td.status-landed").first.wait_for(timeout=60_000)
        cells = row.locator("td").all_inner_texts()
        assert cells[1] == "2d" and cells[6] == "test-linear" and cells[7] == "landed"
        assert cells[2] == ", ".join(f"{v:.2f}" for v in target)
        assert cells[3] != "–" and cells[4] != "–" and cells[5] != "–"  # impact and errors shown
        page.locator("#status", has_text="landed").wait_for(timeout=20_000)

        stored = up.http.get("/api/throws").json()
        assert len(stored) == 1 and stored[0]["target"] == pytest.approx(target.tolist())
        page.screenshot(path=str(tmp_path / "console.png"))
    assert up.returncode == 0
