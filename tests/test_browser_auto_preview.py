"""A failed automatic preview is tried again by itself, in headless Chromium against one `slinger up`
stack (one simulated machine; the tests run in order and share the console page).

The twin's preview fails for real when it starts from a gripper still swinging (after a failed
throw, "clearance violation: ground"); here the page's POST /api/previews is answered, where a test
says so, with the failed preview the server returns then: the real answer's id, machine, mode,
target, policy and start state, ``status`` "failed" with the twin's reason and no prediction
(server.throws.preview_schemas.PreviewOut). The automatic preview itself is the page's own: the
simulated machine is moved (SimReset), the throw gate calls the preview on screen "machine_moved",
and the page previews again (web/js/console.js checkPreview).

* an automatic preview that fails once is tried again about 3 s later, the status line says why,
  and Throw enables with the new preview; the target stays what it was;
* a preview the operator asked for (Preview) that fails is not tried again: its message stays;
* an automatic preview that keeps failing is tried 3 more times, then left to the operator."""

from __future__ import annotations

import time

import pytest

from tests.browser import module_browser, no_page_errors, open_console, press, put_machine_at, set_target  # noqa: F401 (fixtures)
from tests.conftest import SlingerUp, wait_for

pytestmark = [pytest.mark.browser, pytest.mark.usefixtures("no_page_errors")]
T = 180_000  # ms: generous waits for UI state on a loaded 2-core machine
REASON = "clearance violation: ground"
"""The twin's reason for a swing that hit the ground (runtime.executor's clearance check)."""
KEPT = ("id", "machine_id", "mode", "target_m", "policy_version", "policy_sha256", "created_at", "start_q")
"""The fields a failed preview keeps; the prediction fields of PreviewOut are None then."""


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    with SlingerUp(tmp_path_factory.mktemp("auto-preview"), machines=1) as stack:
        stack.wait_machine_online("m1")
        yield stack


@pytest.fixture(scope="module")
def ann(up, module_browser):  # noqa: F811
    """The admin's console with m1 ready; every status line it shows is kept in ``window.__statuses``
    (text, Throw disabled then, page clock ms)."""
    ctx, page = open_console(module_browser, up.base_url, timeout_ms=T)
    page.evaluate("""() => { window.__statuses = [];
        new MutationObserver(() => { const t = document.getElementById('status').textContent;
            const last = window.__statuses[window.__statuses.length - 1];
            if (!last || last.text !== t) window.__statuses.push({ text: t, throwOff: document.getElementById('throw').disabled,
                                                                   at: performance.now() }); })
          .observe(document.getElementById('status'), { subtree: true, childList: true, characterData: true }); }""")
    yield page
    ctx.close()


class FailPreviews:
    """Answer the page's next ``n`` nominal previews (POST /api/previews with ``rollouts`` 1) as
    failed twin swings (the server's real answer with ``status`` "failed", :data:`REASON`);
    every preview request is logged in ``self.seen`` as (wall time s, body, failed)."""

    def __init__(self, page, n: int):
        self.page, self.left, self.seen = page, n, []
        page.route("**/api/previews", self._handle)

    def _handle(self, route) -> None:
        req = route.request
        if req.method != "POST":
            route.continue_()
            return
        body = req.post_data_json
        if body.get("rollouts") != 1 or self.left <= 0:
            self.seen.append((time.time(), body, False))
            route.continue_()
            return
        self.left -= 1
        response = route.fetch()
        real = response.json()
        failed = {k: (real.get(k) if k in KEPT else None) for k in real}
        failed.update(status="failed", reason=REASON)
        self.seen.append((time.time(), body, True))
        route.fulfill(response=response, json=failed)

    def nominals(self) -> list[tuple[float, bool]]:
        """(wall time, failed) of each nominal preview the page asked for since."""
        return [(t, f) for t, b, f in self.seen if b.get("rollouts") == 1]

    def close(self) -> None:
        self.page.unroute("**/api/previews", self._handle)


def _statuses(page, since: int) -> list[dict]:
    return page.evaluate("window.__statuses")[since:]


def _set_target_and_preview(page, x: float, y: float) -> None:
    set_target(page, x, y)
    page.locator("#preview:not([disabled])").wait_for()
    press(page, "#preview")
    page.locator("#throw:not([disabled])").wait_for()


def _cabin(up) -> float:
    return next(m for m in up.http.get("/api/machines").json() if m["id"] == "m1")["cabin_turn_rad"]


def test_a_failed_automatic_preview_is_tried_again_and_throw_enables(up, ann):
    ann.locator("#machine-state", has_text="m1 READY").wait_for()
    _set_target_and_preview(ann, 8.0, 0.0)
    target, fields = ann.evaluate("state.target"), (ann.input_value("#target-x"), ann.input_value("#target-y"))
    first = ann.evaluate("state.preview.id")
    n0 = len(ann.evaluate("window.__statuses"))
    fail = FailPreviews(ann, 1)
    try:
        put_machine_at(up, "m1", [_cabin(up), -0.72, 1.6, 0.6])  # the gate: "machine_moved" -> the page previews again
        # (the route's handler runs while Playwright is waited on: the predicate waits on the page)
        wait_for(lambda: ann.wait_for_timeout(100) or any(f for _, f in fail.nominals()), 90,
                 "the automatic preview (answered failed)")
        ann.locator("#status", has_text="previewing again in 3 s").wait_for(timeout=30_000)
        wait_for(lambda: ann.wait_for_timeout(100) or ann.evaluate("!!(state.preview && state.preview.status === 'ok' && state.preview.id !== "
                                      f"{first!r})") and ann.evaluate("!document.getElementById('throw').disabled"),
                 120, "a new preview of its own and Throw enabled")
    finally:
        fail.close()
    said = [s for s in _statuses(ann, n0) if "previewing again in 3 s" in s["text"]]
    assert said and REASON in said[0]["text"] and "settling" in said[0]["text"], _statuses(ann, n0)
    assert all(s["throwOff"] for s in said), said  # no Throw on a failed preview
    nominals = fail.nominals()
    failed_at = next(t for t, f in nominals if f)
    later = [t for t, f in nominals if t > failed_at]
    assert later and later[0] - failed_at >= 2.5, nominals  # tried again after the delay, not at once
    assert ann.evaluate("state.target") == target  # a preview never changes the target
    assert (ann.input_value("#target-x"), ann.input_value("#target-y")) == fields


def test_a_failed_preview_the_operator_asked_for_is_not_tried_again(up, ann):
    ann.locator("#machine-state", has_text="m1 READY").wait_for()
    ann.locator("#preview:not([disabled])").wait_for()
    n0 = len(ann.evaluate("window.__statuses"))
    fail = FailPreviews(ann, 1)
    try:
        press(ann, "#preview")
        ann.locator("#status", has_text="Preview failed").wait_for()
        ann.wait_for_function("() => !state.busy")
        ann.wait_for_timeout(8000)  # more than the automatic retry's delay, twice
        assert [f for _, f in fail.nominals()] == [True], fail.seen  # the failed one only: no retry
    finally:
        fail.close()
    assert "Preview failed" in ann.inner_text("#status") and REASON in ann.inner_text("#status")
    assert not any("previewing again" in s["text"] for s in _statuses(ann, n0)), _statuses(ann, n0)
    assert ann.locator("#throw").is_disabled()
    assert ann.evaluate("state.retry") is None


def test_an_automatic_preview_that_keeps_failing_is_left_to_the_operator(up, ann):
    ann.locator("#machine-state", has_text="m1 READY").wait_for()
    ann.locator("#preview:not([disabled])").wait_for()
    press(ann, "#preview")  # the operator previews again: this one passes
    ann.locator("#throw:not([disabled])").wait_for()
    fail = FailPreviews(ann, 100)
    try:
        put_machine_at(up, "m1", [_cabin(up), -0.8, 1.6, 0.6])  # back to the ready pose: moved again
        ann.locator("#status", has_text="failed 4 times in a row").wait_for(timeout=120_000)
        ann.wait_for_timeout(8000)
        assert [f for _, f in fail.nominals()] == [True] * 4, fail.seen  # the automatic one and 3 tries
    finally:
        fail.close()
    assert REASON in ann.inner_text("#status") and ann.locator("#throw").is_disabled()
    press(ann, "#preview")  # once the machine has settled, the operator's Preview
    ann.locator("#throw:not([disabled])").wait_for()
