"""Policy versions and fleet in headless Chromium with `slinger up`: an upload rejected with its
reason, an accepted upload, promotion (confirmed first) shown active on the policies and fleet
pages by live push, rollback after a confirmation."""

from __future__ import annotations

import pytest

from tests.conftest import SlingerUp, wait_for
from tests.fixtures import write_test_policy
from tests.browser import browser, log_in  # noqa: F401 (fixture)

pytestmark = pytest.mark.browser


def test_upload_reject_promote_and_rollback(tmp_path, browser):  # noqa: F811
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not onnx at all")
    pa = write_test_policy(tmp_path / "a", "2d", name="pa", seed=1, release_after_bias=2.0)
    pb = write_test_policy(tmp_path / "b", "2d", name="pb", seed=2, release_after_bias=2.0)
    with SlingerUp(tmp_path) as up:
        up.wait_machine_online()
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        log_in(page, up.base_url)
        page.goto(f"{up.base_url}/console/policies.html")
        page.locator("#policies tbody tr").first.wait_for(timeout=10_000)  # test-linear from slinger up

        page.set_input_files("#u-file", str(junk))
        page.fill("#u-name", "junk")
        page.click("#u-submit")
        page.locator("#p-status", has_text="Rejected: Not a loadable ONNX model").wait_for(timeout=10_000)

        for path, name in ((pa, "pa"), (pb, "pb")):
            page.set_input_files("#u-file", str(path))
            page.fill("#u-name", name)
            page.click("#u-submit")
            page.locator("#p-status", has_text=f"accepted: {name}").wait_for(timeout=20_000)
            row = page.locator("#policies tbody tr", has_text=name).first
            row.wait_for(timeout=10_000)
            # a version is promoted only after its validation (its twin evaluation) passed
            wait_for(lambda: any(v["name"] == name and v["evaluation_status"] == "done"
                                 for v in up.http.get("/api/policies").json()), 120, f"{name} validated")
            row.locator("button.promote").click()
            page.locator("#confirm-dialog[open]").wait_for(timeout=10_000)  # promotion asks first
            page.click("#confirm-ok")
            page.locator("#p-status", has_text="m1: offered").wait_for(timeout=10_000)
            wait_for(lambda: up.http.get("/api/machines").json()[0]["policies"].get("2d") == name, 30, f"m1 runs {name}")
            row.locator("td.active-on", has_text="active on m1").wait_for(timeout=20_000)  # pushed live

        page.goto(f"{up.base_url}/console/fleet.html")
        cell = page.locator("#fleet tbody tr[data-machine-id=m1] td.policy-2d")
        cell.filter(has_text="pb").wait_for(timeout=10_000)
        page.click("#fleet tbody tr[data-machine-id=m1] button.rollback-2d")
        page.click("#confirm-dialog[open] button[value=cancel]")  # rollback asks first: cancelled, nothing sent
        page.locator("#fleet-status", has_text="Rollback cancelled").wait_for(timeout=10_000)
        page.click("#fleet tbody tr[data-machine-id=m1] button.rollback-2d")
        page.click("#confirm-ok")
        page.locator("#fleet-status", has_text="rolling m1 back to pa").wait_for(timeout=10_000)
        cell.filter(has_text="pa").wait_for(timeout=30_000)
        page.screenshot(path=str(tmp_path / "fleet.png"))
    assert up.returncode == 0
