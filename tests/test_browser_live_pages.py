"""Console pages follow the server's state, not the answer of one GET: an older answer that lands
after a newer live event never draws over it, a throw the reconciliation closes shows closed, a
shelving that runs out brings its alarm back, a late answer to the banner's Acknowledge or Shelve
does not undo a later change of its alarm, an evaluation that starts shows running, a machine
that comes online joins the diagnosis page's list. Headless Chromium against a live server
(uvicorn in a thread); the GET answers that must land late are held with Playwright's routing."""

from __future__ import annotations

import pytest

from server.fleet.events import RuntimeOffline
from tests.browser import browser, log_in  # noqa: F401 (fixture)
from tests.conftest import wait_for
from tests.test_browser_pages import live  # noqa: F401 (fixture)

pytestmark = pytest.mark.browser


class Held:
    """Playwright route handler: the first request it sees is answered by the server at once
    (its answer is of the server's state then) but handed to the page only on :meth:`release`;
    later requests pass."""

    def __init__(self):
        self.route, self.answer = None, None

    def __call__(self, route) -> None:
        if self.route is not None:
            route.continue_()
            return
        self.answer = route.fetch()
        self.route = route

    def wait(self, page) -> None:
        """Wait (serving the page's events) until a request is held."""
        for _ in range(300):
            if self.route is not None:
                return
            page.wait_for_timeout(100)
        raise AssertionError("no request was held")

    def release(self, page) -> None:
        """Hand the held, older answer to the page and give it time to draw it."""
        self.route.fulfill(response=self.answer)
        page.wait_for_timeout(1500)


BREAKABLE_STREAM = """(() => { const ES = window.EventSource; window.liveSources = [];
  window.EventSource = class extends ES { constructor(...a) { super(...a); window.liveSources.push(this); } }; })();"""
"""An init script that keeps the page's EventSource objects in ``window.liveSources``, so a test can
break the live stream as a lost connection does (closed, an ``error`` event)."""


def _page(browser, base, path):  # noqa: F811
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.set_default_timeout(30_000)
    log_in(page, base, start="/console/account.html")
    page.goto(f"{base}/console/{path}")
    return page


def test_the_alarm_banner_keeps_an_alarm_raised_while_its_alarms_were_being_fetched(live, browser):  # noqa: F811
    base, app = live
    app.state.alarms.on_event(RuntimeOffline("m1"))
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base, start="/console/account.html")
    held = Held()
    page.route("**/api/alarms", held)  # on the fleet page only the status strip asks for the alarms
    page.goto(f"{base}/console/fleet.html")
    held.wait(page)
    app.state.alarms.on_event(RuntimeOffline("m2"))  # raised after the server answered the held GET
    page.locator("#alarm-top", has_text="m2: runtime offline").wait_for()  # its event: the one alarm known yet
    held.release(page)
    assert page.locator("#alarm-count").inner_text().startswith("ALARMS 2")


def test_the_alarms_page_never_draws_an_older_answer_over_a_newer_one(live, browser):  # noqa: F811
    base, app = live
    first = app.state.alarms.raise_alarm("k:a", "m1", "high", "machine_fault", "m1: first", "text", "todo")
    page = _page(browser, base, "alarms.html")
    row = f"#alarm-table tbody tr[data-alarm-id='{first['id']}']"
    page.locator(row, has_text="active, not acknowledged").wait_for()
    held = Held()
    page.route(lambda url: "/api/alarms?active=false" in url, held)  # the page's own list (the strip asks for the active ones)
    page.select_option("#alarm-scope", "all")
    held.wait(page)  # the server answered: the first alarm not acknowledged
    app.state.alarms.acknowledge(first["id"], "admin")  # its event asks again; that answer is drawn
    page.locator(row, has_text="active, acknowledged").wait_for()
    held.release(page)
    assert "active, acknowledged" in page.locator(row).inner_text()


def test_a_shelved_alarm_comes_back_when_its_shelving_runs_out(live, browser):  # noqa: F811
    base, app = live
    a = app.state.alarms.raise_alarm("k:s", "m1", "high", "machine_fault", "m1: shelved one", "text", "todo")
    page = _page(browser, base, "alarms.html")
    row = f"#alarm-table tbody tr[data-alarm-id='{a['id']}']"
    page.locator("#alarm-top", has_text="m1: shelved one").wait_for()
    app.state.alarms.shelve(a["id"], "admin", 3 / 60)  # 3 s; the server publishes nothing when it ends
    page.locator("#alarm-banner").wait_for(state="hidden")
    page.locator(row, has_text="(shelved)").wait_for()
    page.locator("#alarm-top", has_text="m1: shelved one").wait_for(timeout=20_000)
    page.locator(row, has_text="active, not acknowledged").wait_for(timeout=20_000)
    assert "(shelved)" not in page.locator(row).inner_text()


def test_the_fleet_page_shows_a_throw_the_reconciliation_closed_as_lost(live, browser, fake_runtime_factory):  # noqa: F811
    from server.db.models import Machine, Throw

    base, app = live
    reconciler = app.state.reconciler
    reconciler.stop()  # passes by hand only
    reconciler.handshake_s, reconciler.result_grace_s = 0.0, 0.0
    with app.state.sessions.begin() as db:  # a throw its runtime never took (no answer to its request)
        db.add(Machine(id="m1", simulated=True))
        db.add(Throw(id="t-lost", machine_id="m1", mode="2d", status="requested", target_x_m=8.0, target_y_m=0.0,
                     target_z_m=0.0))
    fake_runtime_factory()
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    page = _page(browser, base, "fleet.html")
    row = "#fleet tbody tr[data-machine-id=m1]"
    page.locator(row, has_text="requested)").wait_for()
    page.wait_for_function("() => Live.isConnected()")
    assert [tid for tid, _ in reconciler.run_once()] == ["t-lost"]
    page.locator(row, has_text="lost)").wait_for(timeout=20_000)


def test_the_diagnosis_page_never_shows_a_finished_run_running(live, browser):  # noqa: F811
    from server.jobs.leases import WorkerIdentity

    base, app = live
    store = app.state.jobs.store
    run_id = store.create("diagnosis", {"machine_id": "m1", "limit": 30}, subject="m1")
    page = _page(browser, base, "diagnosis.html")
    row = f"#runs tbody tr:has(a[href='#{run_id}'])"
    page.locator(row, has_text="queued").wait_for()
    held = Held()
    page.route("**/api/diagnosis/runs", held)
    store.start(run_id, WorkerIdentity())  # its job event asks for the runs: answered "running", held
    held.wait(page)
    store.finish(run_id, "done", result={"throws": 30, "verdict": None})
    page.locator(row, has_text="done").wait_for()
    held.release(page)
    assert "done" in page.locator(row).inner_text()


def test_the_diagnosis_page_lists_a_machine_that_came_online_after_it_opened(live, browser, fake_runtime_factory):  # noqa: F811
    base, app = live
    page = _page(browser, base, "diagnosis.html")
    page.wait_for_function("() => Live.isConnected()")
    assert page.locator("#machine_id option").count() == 0
    fake_runtime_factory(machine_id="m7")
    page.locator("#machine_id option[value=m7]").wait_for(state="attached", timeout=20_000)


def test_the_policies_page_shows_an_evaluation_running_once_it_runs(live, browser):  # noqa: F811
    from server.db.models import PolicyVersion

    base, app = live
    with app.state.sessions.begin() as db:
        p = PolicyVersion(name="pX", mode="2d", sha256="ab" * 32, manifest={}, evaluation_status="pending")
        db.add(p)
        db.flush()
        pid = p.id
    page = _page(browser, base, "policies.html")
    cell = f"#policies tbody tr[data-policy-id='{pid}'] td.eval"
    page.locator(cell, has_text="pending").wait_for()
    with app.state.sessions.begin() as db:
        db.get(PolicyVersion, pid).evaluation_status = "running"
    # the evaluation's progress, as the job watcher publishes it (server.jobs.watch)
    app.state.live.publish("job", {"id": "j1", "kind": "evaluation", "status": "running", "subject": str(pid),
                                   "progress": 0.0, "message": "validation", "error": None, "requested_by": "admin"})
    page.locator(cell, has_text="running").wait_for(timeout=20_000)


def test_the_history_page_reads_a_listed_throw_again_when_it_ends(live, browser):  # noqa: F811
    from server.db.models import Machine, Throw

    base, app = live
    with app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.add(Throw(id="t-run", machine_id="m1", mode="2d", status="swinging", target_x_m=8.0, target_y_m=0.0,
                     target_z_m=0.0))
    page = _page(browser, base, "history.html?throw=t-run")
    row = "#throws tbody tr[data-throw-id=t-run]"
    page.locator(row, has_text="swinging").wait_for()
    page.locator("#d-id", has_text="swinging").wait_for()
    page.wait_for_function("() => Live.isConnected()")
    with app.state.sessions.begin() as db:
        t = db.get(Throw, "t-run")
        t.status, t.failure_reason = "lost", "runtime of m1 is not running the throw"
    app.state.live.throw_closed("t-run")  # as the reconciliation announces it
    page.locator(row, has_text="lost").wait_for(timeout=20_000)
    page.locator("#d-id", has_text="lost").wait_for(timeout=20_000)


def test_the_console_shows_the_end_of_its_throw_that_came_while_the_server_was_unreachable(live, browser, fake_runtime_factory):  # noqa: F811
    from server.db.models import Machine, Throw

    base, app = live
    with app.state.sessions.begin() as db:  # before its runtime comes online (the server adds a new machine's row then)
        db.add(Machine(id="m1", simulated=True))
        db.add(Throw(id="t-run", machine_id="m1", mode="2d", status="swinging", target_x_m=8.0, target_y_m=0.0,
                     target_z_m=0.0))
    fake_runtime_factory()
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.set_default_timeout(30_000)
    page.add_init_script(BREAKABLE_STREAM)
    log_in(page, base, start="/console/account.html")
    page.goto(f"{base}/console/index.html")
    page.wait_for_function("() => Live.isConnected() && state.machineId === 'm1'")
    # the throw this console sent, running (as after its Throw button: doThrow)
    page.evaluate("() => { state.throwId = 't-run'; state.throwStarted = Date.now(); startThrowPanel('t-run'); }")
    page.route("**/api/live*", lambda route: route.abort())  # the server unreachable ...
    page.evaluate("() => { const s = window.liveSources.at(-1); s.close(); s.dispatchEvent(new Event('error')); }")
    page.locator("#server-banner").wait_for(state="visible")
    with app.state.sessions.begin() as db:
        t = db.get(Throw, "t-run")
        t.status, t.failure_reason = "lost", "runtime of m1 is not running the throw"
    app.state.live.throw_closed("t-run")  # not heard: the page is cut off
    page.unroute("**/api/live*")  # ... and back: the page's next try connects
    page.locator("#tp-result", has_text="LOST").wait_for(timeout=30_000)
    assert page.evaluate("() => state.throwId") is None  # no throw in flight: the page judges and previews again


def test_the_fleet_page_offers_the_rollback_the_server_would_make_once_a_promotion_is_confirmed(live, browser, fake_runtime_factory):  # noqa: F811
    import time
    from datetime import timedelta

    from runtime.protocol import keys
    from runtime.protocol.messages import PolicyInfo, PolicyUpdate, encode
    from server.db.models import Machine, PolicyDeployment, PolicyVersion
    from server.db.types import utcnow

    base, app = live
    sha = {"pZ": "0" * 64, "pA": "a" * 64, "pB": "b" * 64}
    with app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        ids = {}
        for name, s in sha.items():
            v = PolicyVersion(name=name, mode="2d", sha256=s, manifest={})
            db.add(v)
            db.flush()
            ids[name] = v.id
        t0 = utcnow() - timedelta(minutes=5)
        db.add(PolicyDeployment(machine_id="m1", mode="2d", policy_version_id=ids["pA"], previous_sha256=sha["pZ"],
                                status="active", requested_at=t0))
        db.add(PolicyDeployment(machine_id="m1", mode="2d", policy_version_id=ids["pB"], previous_sha256=sha["pA"],
                                status="offered", requested_at=t0 + timedelta(minutes=1)))
    # the runtime runs pB already; its PolicyUpdate ("loaded") has not been handled yet
    rt = fake_runtime_factory(policies=[PolicyInfo(mode="2d", version="pB", sha256=sha["pB"])])
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    page = _page(browser, base, "fleet.html")
    page.locator("#fleet tbody tr[data-machine-id=m1] button.rollback-2d", has_text="roll back to pZ").wait_for()
    page.wait_for_function("() => Live.isConnected()")
    update = PolicyUpdate(machine_id="m1", stamp_s=time.monotonic(), mode="2d", version="pB", sha256=sha["pB"], status="loaded")
    rt.session.put(keys.policy_status("m1"), encode(update))  # the runtime's word: pB loaded
    wait_for(lambda: app.state.policies.rollback_target("m1", "2d").name == "pA", 20, "pB's deployment active")
    page.locator("#fleet tbody tr[data-machine-id=m1] button.rollback-2d", has_text="roll back to pA").wait_for(timeout=20_000)


def _banner_act_held(browser, base, app, key: str, title: str, act: str):  # noqa: F811
    """Raise alarm ``key`` (``title``), open the fleet page and press the banner's ``act`` button
    ("ack" or "shelve") with its answer held (the server has acted; the page has not heard it).
    Returns (page, alarm, held)."""
    alarm = app.state.alarms.raise_alarm(key, "m1", "high", "machine_fault", title, "text", "todo")
    page = _page(browser, base, "fleet.html")
    page.locator("#alarm-top", has_text=title).wait_for()
    held = Held()
    page.route(f"**/api/alarms/{alarm['id']}/{act}", held)
    page.click("#alarm-toggle")
    page.click(f"#alarms .alarm-{act}")
    held.wait(page)
    return page, alarm, held


def test_the_banner_drops_an_acknowledgement_answer_older_than_the_alarms_end(live, browser):  # noqa: F811
    """The answer to the banner's Acknowledge is held back while the condition clears: the alarm,
    cleared and acknowledged, leaves the active list (its live event empties the banner); the older
    answer (active, acknowledged) that lands afterwards must not bring it back."""
    base, app = live
    page, _, held = _banner_act_held(browser, base, app, "k:stale-ack", "m1: stale ack", "ack")
    app.state.alarms.clear("k:stale-ack")  # cleared and acknowledged: history only
    page.locator("#alarm-banner").wait_for(state="hidden")
    held.release(page)
    assert page.locator("#alarm-banner").is_hidden(), page.locator("#alarm-count").inner_text()


def test_the_banner_drops_a_shelving_answer_older_than_the_unshelving_it_heard(live, browser):  # noqa: F811
    """The answer to the banner's Shelve is held back while another operator unshelves the alarm:
    its live events (shelved, then unshelved) come first and the alarm is back in the banner; the
    older answer (shelved) that lands afterwards must not hide it again (the records' revisions
    order them)."""
    base, app = live
    page, alarm, held = _banner_act_held(browser, base, app, "k:stale-shelve", "m1: stale shelve", "shelve")
    page.locator("#alarm-banner").wait_for(state="hidden")  # the shelving's live event hides it
    app.state.alarms.unshelve(alarm["id"], "someone-else")
    page.locator("#alarm-top", has_text="m1: stale shelve").wait_for()
    held.release(page)
    assert page.locator("#alarm-top").inner_text().endswith("m1: stale shelve")
