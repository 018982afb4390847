"""The operator console in headless Chromium: preview numbers and ellipse, refusal reasons, 3D
confirmation, throw as previewed, E-stop; viewers see no operator controls. Targets are typed
(the click-to-target path is covered by test_browser.py)."""

from __future__ import annotations

import pytest

from tests.conftest import SlingerUp, add_user_cli
from tests.test_browser import browser, log_in  # noqa: F401 (fixture)

pytestmark = pytest.mark.browser


def type_target(page, x: float, y: float) -> None:
    page.fill("#target-x", str(x))
    page.fill("#target-y", str(y))
    page.click("#target-set")
    page.locator("#target", has_text=f"x {x:.2f}").wait_for(timeout=10_000)


def test_preview_refusal_3d_confirmation_throw_and_estop(tmp_path, browser):  # noqa: F811
    with SlingerUp(tmp_path, with_3d=True) as up:
        up.wait_machine_online()
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        log_in(page, up.base_url)
        page.locator("#machine-online", has_text="online").wait_for(timeout=20_000)

        # a target the 2D mode cannot serve: refused with the reason, nothing moves
        type_target(page, 3.0, -0.29)
        page.locator("#preview:not([disabled])").wait_for(timeout=20_000)
        page.click("#preview")
        page.locator("#status", has_text="too close").wait_for(timeout=10_000)
        assert page.locator("#throw").is_disabled()
        type_target(page, 6.0, 5.0)
        page.click("#preview")
        page.locator("#status", has_text="2D throwing plane").wait_for(timeout=10_000)

        # a good target: numbers first, then the ellipse; the 3D view draws it
        type_target(page, 8.0, -0.29)
        page.click("#preview")
        page.locator("#pv-sigma", has_text="200 rollouts").wait_for(timeout=20_000)
        for sel in ("#pv-down", "#pv-cross", "#pv-duration"):
            assert page.locator(sel).inner_text().endswith(("m", ")")), sel
        assert "boom" in page.locator("#pv-speeds").inner_text()
        assert len(page.locator("#pv-ellipse").get_attribute("points").split()) == 65
        scene = up.http.get("/api/scene").json()
        assert {"/preview/gripper_path", "/preview/payload_path", "/preview/release_velocity",
                "/preview/impact", "/preview/ellipse"} <= set(scene["preview"])

        # throw as previewed
        page.click("#throw")
        page.locator("#status", has_text="accepted").wait_for(timeout=15_000)
        page.locator("#history tbody td.status-landed").first.wait_for(timeout=60_000)
        row = up.http.get("/api/throws").json()[0]
        assert row["preview"] is not None and row["preview"]["target_m"] == pytest.approx([8.0, -0.29, 0.0])

        # 3D: the clearance zone is drawn and the throw needs the explicit confirmation
        page.check("input[name=mode][value='3d']")
        page.locator("#confirm-box").wait_for(state="visible", timeout=20_000)
        type_target(page, 7.0, 3.0)
        page.click("#preview")
        page.locator("#pv-sigma", has_text="rollouts").wait_for(timeout=20_000)
        assert "/preview/clearance_zone" in up.http.get("/api/scene").json()["preview"]
        assert page.locator("#throw").is_disabled()
        page.check("#confirm-clearance")
        page.locator("#throw:not([disabled])").wait_for(timeout=20_000)

        # E-stop is there at any time and logged
        page.click("#abort")
        page.locator("#status", has_text="STOPPED m1").wait_for(timeout=10_000)
        assert up.http.get("/api/audit", params={"action": "abort"}).json()[0]["subject"] == "m1"
        page.screenshot(path=str(tmp_path / "console-preview.png"))

        # a viewer sees the machine but none of the operator controls
        add_user_cli(up, "vera", "viewer-pass", "viewer")
        viewer = browser.new_page(viewport={"width": 1400, "height": 900})
        log_in(viewer, up.base_url, ("vera", "viewer-pass"))
        viewer.locator("#machine-online", has_text="online").wait_for(timeout=20_000)
        assert not viewer.locator("#abort").is_visible() and not viewer.locator("#preview").is_visible()
    assert up.returncode == 0
