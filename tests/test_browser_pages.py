"""History, accuracy, policies, fleet and users pages in headless Chromium against a live server
(uvicorn in a thread, no 3D view, no runtime; rows are written straight into the database; a
drift alert is raised through the server's drift watch)."""

from __future__ import annotations

import re
import threading
from datetime import UTC, datetime, timedelta

import pytest

from server.db.models import Machine, Throw
from tests.browser import SIZES, axe_serious, browser, log_in  # noqa: F401 (fixture)
from tests.conftest import ADMIN, add_user, free_port, wait_for
from tests.fixtures import finished_diagnosis_run, raise_drift_alert, write_swing_telemetry

pytestmark = pytest.mark.browser


@pytest.fixture
def live(settings):
    """The app served by uvicorn on a free port: yields (base_url, app)."""
    yield from _serve(settings)


@pytest.fixture
def live_3d(settings):
    """:func:`live` with the 3D view (viser) on a free port."""
    settings.viser_enabled, settings.viser_port = True, free_port()
    yield from _serve(settings)


def _serve(settings):
    import uvicorn

    from server.app import create_app

    settings.port = free_port()
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=settings.port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 30, "uvicorn started")
    add_user(app.state.sessions, *ADMIN, "admin")
    yield f"http://127.0.0.1:{settings.port}", app
    server.should_exit = True
    thread.join(timeout=15)


def _seed(app, n: int = 30) -> None:
    t0 = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)
    with app.state.sessions.begin() as db:
        db.add_all([Machine(id="m1", simulated=True), Machine(id="m2", simulated=True)])
        for i in range(n):
            d = 7.5 + 0.5 * (i % 4)
            db.add(Throw(id=f"t{i:02d}", machine_id="m1" if i % 2 else "m2", mode="2d", target_x_m=d, target_y_m=0.0,
                         target_z_m=0.0, status="landed", downrange_error_m=0.02 * (i % 5) - 0.04,
                         crossrange_error_m=0.01 * (i % 3) - 0.01, impact_x_m=d, impact_y_m=0.0, impact_z_m=0.0,
                         policy_version="pA", requested_at=t0 + timedelta(minutes=i), duration_s=2.0,
                         preview={"downrange_error_m": 0.123, "crossrange_error_m": 0.0, "impact_m": [d, 0, 0],
                                  "payload_path_m": [[5, 0, 2], [d, 0, 0]]} if i == 29 else None))


def test_history_filter_sort_page_detail_and_accuracy(live, browser):  # noqa: F811
    base, app = live
    _seed(app)
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base)
    page.goto(f"{base}/console/history.html")
    page.locator("#page-info", has_text="page 1 of 2 (30 throws)").wait_for(timeout=10_000)
    assert page.locator("#throws tbody tr").count() == 25
    page.click("#next")
    page.locator("#page-info", has_text="page 2 of 2").wait_for(timeout=10_000)
    assert page.locator("#throws tbody tr").count() == 5
    # filter by machine: the server filters (15 of 30)
    page.fill("#f-machine_id", "m1")
    page.click("#apply")
    page.locator("#page-info", has_text="(15 throws)").wait_for(timeout=10_000)
    assert set(page.locator("#throws tbody tr td:nth-child(2)").all_inner_texts()) == {"m1"}
    assert "machine_id=m1" in page.locator("#csv").get_attribute("href")
    # sort by target distance, ascending after two clicks
    th = page.locator("th[data-sort=target_distance]")
    th.click()
    page.locator("th.sorted[data-order=desc]").wait_for(timeout=20_000)
    th.click()
    page.locator("th.sorted[data-order=asc]").wait_for(timeout=20_000)
    page.wait_for_timeout(300)
    assert page.locator("#throws tbody tr td:nth-child(5)").first.inner_text() == "8.00"  # m1: 8 and 9 m
    # detail: preview against what happened
    page.fill("#f-machine_id", "")
    page.click("#apply")
    page.locator("#page-info", has_text="(30 throws)").wait_for(timeout=10_000)
    page.locator("th[data-sort=requested_at]").click()
    page.locator("#throws tbody tr[data-throw-id=t29]").click()
    page.locator("#d-pred-down", has_text="0.12").wait_for(timeout=10_000)
    assert page.locator("#d-act-down").inner_text() == "0.04"
    page.locator("#d-noplot").wait_for(timeout=10_000)  # no telemetry: said so, no empty plots

    page.goto(f"{base}/console/accuracy.html")
    page.locator("svg.acc-plot[data-key='2d · pA']").wait_for(timeout=10_000)
    assert page.locator("#accuracy tbody tr").count() == 4
    assert page.locator("svg.err-plot polyline.ell").count() == 4


def test_viewer_cannot_see_admin_pages_controls(live, browser):  # noqa: F811
    base, app = live
    add_user(app.state.sessions, "vera", "viewer-pass-1", "viewer")
    page = browser.new_page()
    log_in(page, base, ("vera", "viewer-pass-1"))
    assert not page.locator("nav a[href='admin.html']").is_visible()
    page.goto(f"{base}/console/login.html")
    page.fill("#username", "vera")
    page.fill("#password", "wrong-password")
    page.click("#login")
    page.locator("#login-error", has_text="invalid user name or password").wait_for(timeout=10_000)


def test_diagnosis_page_is_linked_everywhere_and_refuses_a_machine_without_throws(live, browser):  # noqa: F811
    base, app = live
    _seed(app, n=3)  # rows without telemetry: nothing the diagnosis can replay
    page = browser.new_page()
    log_in(page, base)
    for name in ("history", "accuracy", "policies", "fleet", "admin"):
        page.goto(f"{base}/console/{name}.html")
        page.locator('nav a[href="diagnosis.html"]').wait_for(state="attached", timeout=20_000)
        assert page.locator('nav a[href="diagnosis.html"]').count() == 1, name
    page.goto(f"{base}/console/diagnosis.html")
    page.locator("#machine_id option[value=m1]").wait_for(state="attached", timeout=20_000)
    page.select_option("#machine_id", "m1")  # picked from the list of machines
    page.click("#start button[type=submit]")
    msg = page.locator("#start-msg")
    wait_for(lambda: msg.text_content() not in ("", "exporting throws…"), 20, "diagnosis start answered")
    text = msg.text_content()
    assert "throw" in text.lower() and "started" not in text, text  # the reason names the missing throws
    page.close()


def test_history_replay_drives_the_3d_view_along_the_plots_timeline(live_3d, browser):  # noqa: F811
    """Seek, play and pause on the History page's timeline move the plots' cursor and the 3D
    view's machine together; the page says the time the 3D view shows (``data-shown-t``, from the
    server's answer) and the scene's drawn pose is the recording's at that time."""
    import numpy as np

    base, app = live_3d
    t, q = write_swing_telemetry(app.state.settings.data_dir / "telemetry" / "th-1.mcap")
    with app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.add(Throw(id="th-1", machine_id="m1", mode="2d", target_x_m=8.2, target_y_m=0.4, target_z_m=0.0, status="landed",
                     impact_x_m=8.0, impact_y_m=0.5, impact_z_m=0.0, downrange_error_m=-0.2, crossrange_error_m=0.1,
                     duration_s=2.0, telemetry_path="telemetry/th-1.mcap", requested_at=datetime(2026, 5, 1, 12, tzinfo=UTC)))
    page = browser.new_page(viewport={"width": 1440, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    log_in(page, base, start="/console/history.html?throw=th-1")
    page.locator("#replay-view[data-shown-t='0.000']").wait_for(timeout=30_000)
    assert page.locator("#strip").is_visible()
    speed = page.locator(".replay-speed select")
    assert page.locator(".replay-speed").inner_text().startswith("speed")
    assert speed.locator("option:checked").inner_text() == "0.25× real time"
    (cid,) = list(app.state.scene.consoles)
    scene = app.state.scene
    drawn = lambda k: wait_for(lambda: any(p is not None and np.allclose(p, q[k], atol=1e-6) for p in scene.drawn_poses(cid)),  # noqa: E731
                               30, f"the 3D machine at t = {t[k]} s")
    drawn(0)  # the 3D view connected and shows the start of the recording
    # 1x plays in real time on a busy page: its timer ticks come late (the main thread blocked
    # 100 ms of every 120 ms), the recorded time still follows the clock
    speed.select_option("1")
    ratio = page.evaluate("""() => new Promise((resolve) => {
        const jank = setInterval(() => { const until = performance.now() + 100; while (performance.now() < until) {} }, 120);
        const t0 = performance.now(); document.getElementById('scrub-play').click();
        setTimeout(() => { document.getElementById('scrub-play').click(); clearInterval(jank);
            const k = Number(document.getElementById('scrub').value);
            resolve([k, (performance.now() - t0) / 1000]); }, 1000); })""")
    played = t[ratio[0]] - t[0]
    assert 0.7 < played / ratio[1] < 1.3, f"1x played {played:.2f} s of recording in {ratio[1]:.2f} s"
    speed.select_option("0.25")
    page.eval_on_selector("#scrub", "(e) => { e.value = 100; e.dispatchEvent(new Event('input')); }")  # seek to t = 1 s
    page.locator("#replay-view[data-shown-t='1.000']").wait_for(timeout=20_000)
    drawn(100)
    assert "t = 1.00 s" in page.locator("#scrub-readout").inner_text()  # the plots' cursor at the same time
    assert not np.allclose(q[100], q[0])  # the machine really moved between the two times
    page.click("#scrub-play")  # at 0.25x: the 1 s left of the recording takes 4 s
    page.wait_for_function("() => Number(document.querySelector('#replay-view').dataset.shownT) >= 1.2", timeout=30_000)
    page.click("#scrub-play")  # pause
    assert page.locator("#scrub-play").inner_text() == "Play"
    page.wait_for_timeout(500)
    shown = float(page.locator("#replay-view").get_attribute("data-shown-t"))
    page.wait_for_timeout(500)
    assert float(page.locator("#replay-view").get_attribute("data-shown-t")) == shown  # paused: both stand still
    k = int(page.eval_on_selector("#scrub", "(e) => Number(e.value)"))
    assert shown == pytest.approx(t[k], abs=1e-3)  # the 3D view shows the plots' sample
    drawn(k)
    assert errors == [], errors
    page.close()


def test_a_drift_alarm_shows_on_every_open_console_until_an_operator_acknowledges_it(live, browser):  # noqa: F811
    """Two consoles (two browsers' worth of contexts: no shared storage) on two pages; the alert
    comes through server.analysis.drift's own input; Acknowledge in one clears it in both; a viewer's
    press is refused with a sentence."""
    base, app = live
    _seed(app, n=3)
    add_user(app.state.sessions, "vera", "viewer-pass-1", "viewer")
    pages = []
    for user, start in ((ADMIN, "/console/history.html"), (("vera", "viewer-pass-1"), "/console/diagnosis.html")):
        ctx = browser.new_context(viewport={"width": 1440, "height": 900})
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e, errors=errors: errors.append(str(e)))
        log_in(page, base, user, start)
        page.locator("#strip-link", has_text=re.compile("link: (OK|m1 offline)")).wait_for(timeout=30_000)  # live
        pages.append((page, errors))
    (admin_page, _), (viewer_page, _) = pages
    alert = raise_drift_alert(app.state.drift, "m1")
    for page, _ in pages:
        page.locator("#alarm-top", has_text="m1: accuracy drift").wait_for(timeout=20_000)
        page.click("#alarm-toggle")
        assert alert["text"] in page.locator("#alarms li.alarm").first.inner_text()
    viewer_page.click("#alarms li.alarm button.alarm-ack")
    viewer_page.locator("#strip-msg", has_text="needs the operator role").wait_for(timeout=20_000)
    assert viewer_page.locator("#alarms li.alarm").count() == 1 and app.state.drift.alert("m1")["status"] == "open"
    viewer_page.reload()  # a console opened later gets the open alert too
    viewer_page.locator("#alarm-top", has_text="m1: accuracy drift").wait_for(timeout=20_000)
    admin_page.click("#alarms li.alarm button.alarm-ack")
    for page, _ in pages:
        page.locator("#alarm-banner").wait_for(state="hidden", timeout=20_000)
    admin_page.locator("#strip-msg", has_text="Drift alert of m1 acknowledged.").wait_for(timeout=20_000)
    assert app.state.drift.alert("m1")["acknowledged_by"] == ADMIN[0]
    admin_page.goto(f"{base}/console/admin.html")  # the acknowledgement is in the audit log
    admin_page.locator("#audit tbody tr", has_text="drift ack").first.wait_for(timeout=20_000)
    assert admin_page.locator("#alarms li.alarm").count() == 0  # and stays acknowledged on a new page
    for page, errors in pages:
        assert errors == [], errors
        page.context.close()


def test_alarms_on_a_phone_stay_within_a_sixth_and_hide_no_control(live, browser):  # noqa: F811
    """Four alarms on a 390x844 phone: the banner (its list opened too) takes at most a sixth of
    the viewport and covers none of the console's controls; acknowledge-all acknowledges them all
    on the server (who, when), the Alarms page lists them with who acknowledged."""
    from server.fleet.events import RuntimeOffline

    base, app = live
    _seed(app, n=3)
    for mid in ("m1", "m2", "m3", "m4"):
        app.state.alarms.on_event(RuntimeOffline(mid))
    ctx = browser.new_context(viewport={"width": 390, "height": 844}, has_touch=True, is_mobile=True)
    page = ctx.new_page()
    log_in(page, base, ADMIN, "/console/index.html")
    page.locator("#alarm-count", has_text="ALARMS 4").wait_for(timeout=30_000)
    problems = []
    for opened in (False, True):
        if opened:
            page.click("#alarm-toggle")
            page.locator("#alarms li").nth(3).wait_for(state="attached")
        h = page.evaluate("document.getElementById('alarm-banner').getBoundingClientRect().height")
        if h > 844 / 6:
            problems.append(f"banner {h:.0f} px tall (list {'open' if opened else 'closed'})")
        for sel in ("#preview", "#throw", "#target-x", "#target-set", "#estop"):
            hidden = page.evaluate("""(sel) => { const e = document.querySelector(sel); e.scrollIntoView({ block: 'center' });
                const r = e.getBoundingClientRect(); const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
                return !(hit === e || e.contains(hit)); }""", sel)
            if hidden:
                problems.append(f"{sel} covered (list {'open' if opened else 'closed'})")
    assert problems == [], problems
    page.click("#alarm-ack-all")
    page.locator("#strip-msg", has_text="4 alarms acknowledged").wait_for(timeout=20_000)
    assert all(a["acked_by"] == ADMIN[0] for a in app.state.alarms.active())
    page.goto(f"{base}/console/alarms.html")
    page.locator("#alarm-table tbody tr", has_text=f"by {ADMIN[0]}").nth(3).wait_for(timeout=20_000)
    ctx.close()


PAGES = ["history.html?throw=t29", "accuracy.html", "policies.html", "fleet.html", "admin.html", "diagnosis.html",
         "alarms.html"]


def test_every_page_is_accessible_and_fits_three_sizes(live, browser):  # noqa: F811
    """axe-core: no serious or critical violation on any page; at 1440, 1024 and 390 px wide no
    page scrolls sideways. With SLINGER_SCREENSHOTS=DIR the pages are also photographed there
    (the set under reports/screenshots/ is made this way)."""
    import os

    base, app = live
    _seed(app)
    shots = os.environ.get("SLINGER_SCREENSHOTS")
    page = browser.new_page(viewport={"width": 1440, "height": 900})
    page.goto(f"{base}/console/login.html")
    assert axe_serious(page) == [], "login"
    for w, h in SIZES if shots else ():
        page.set_viewport_size({"width": w, "height": h})
        page.screenshot(path=f"{shots}/login-{w}x{h}.png")
    page.set_viewport_size({"width": 1440, "height": 900})
    log_in(page, base, start="/console/history.html")
    problems = []
    for name in PAGES:
        page.goto(f"{base}/console/{name}")
        page.locator("#who", has_text="admin").wait_for(timeout=20_000)
        page.wait_for_timeout(300)
        problems += [f"{name}: {v}" for v in axe_serious(page)]
        for w, h in SIZES:
            page.set_viewport_size({"width": w, "height": h})
            page.wait_for_timeout(150)
            scroll_w = page.evaluate("document.documentElement.scrollWidth")
            if scroll_w > w:
                wide = page.evaluate("""(w) => [...document.querySelectorAll('body *')].filter(e => e.getBoundingClientRect().right > w + 1 && !(e.parentElement && e.parentElement.closest('.table-wrap, .uplot')))
                    .slice(0, 4).map(e => e.tagName + (e.id ? '#' + e.id : '') + '.' + e.className)""", w)
                problems.append(f"{name} at {w}x{h}: page {scroll_w} px wide ({', '.join(wide)})")
            if shots:
                page.screenshot(path=f"{shots}/{name.split('.')[0]}-{w}x{h}.png", full_page=False)
        page.set_viewport_size({"width": 1440, "height": 900})
    assert problems == []


def _fake_run(state) -> str:
    """A finished diagnosis run (its job row and report): two rounds (one named, one ambiguous
    with an at-bound candidate); returns its id."""
    cand = lambda e, wins, adm, reason="", at=(), p=None: {  # noqa: E731
        "effect": e, "params": p or {"x": 1.0}, "sigma": {"x": 0.1}, "at_bound": list(at), "worse": {}, "wins": wins, "beats_none": wins,
        "admissible": adm, "reason": reason, "k": 1}
    report = {
        "verdict": {"answer": "ambiguous", "text": "valve_lag (…) then ambiguous between wind and payload_drag", "between": ["wind", "payload_drag"],
                    "measurement": "track the payload in flight (/payload)", "effects": ["valve_lag"]},
        "where": {"gap": True, "carriers": ["q.boom", "impact.downrange"], "phases": {"swing": 0.7, "release": 0.1, "flight": 0.2},
                  "noise": {"sigma": {"q.boom": 0.002}, "impact_sigma_m": 0.05},
                  "channels": {"q.boom": {"chi2": 900.0, "dof": 300.0, "gap": True, "by_phase": {"swing": {"chi2": 800.0, "dof": 200.0}}},
                               "impact.downrange": {"chi2": 90.0, "dof": 28.0, "gap": True, "by_phase": {"flight": {"chi2": 90.0, "dof": 28.0}}}}},
        "rounds": [{"decision": "named", "named": "valve_lag", "wins_none": 0.0, "gated_out": {"wind": "acts on impact"},
                    "candidates": [cand("valve_lag", 0.93, True), cand("hanging_mass", 0.07, False, "at its prior bound: gripper_mass_kg", ["x"])]},
                   {"decision": "ambiguous", "named": "wind", "wins_none": 0.05, "gated_out": {},
                    "candidates": [cand("wind", 0.55, True), cand("payload_drag", 0.4, True)]}],
        "how_far": {"test_throws": ["a", "b", "c"], "chi2_excess_before": 500.0, "chi2_excess_after": 50.0, "gap_shrink": 0.9,
                    "impact_rms_m": {"before": 0.3, "after": 0.1}, "impact_gap_shrink": 0.67, "share_of_shrink": {"valve_lag": 0.8},
                    "accuracy": {"observed": {}, "replayed_nominal": {}, "replayed_fitted": {}}},
        "plots": {},
    }
    return finished_diagnosis_run(state, "m1", report)


def test_diagnosis_page_shows_where_verdict_evidence_and_shrink(live, browser):  # noqa: F811
    base, app = live
    run_id = _fake_run(app.state)
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base)
    page.goto(f"{base}/console/diagnosis.html#{run_id}")
    page.locator("#r-verdict", has_text="ambiguous between wind and payload_drag").wait_for(timeout=20_000)
    summary = page.locator("#r-summary").text_content()  # plain words first: what, how sure, what to do
    assert "valve lag" in summary and "93%" in summary and "What to do" in summary, summary
    assert page.locator("#r-details").get_attribute("open") is None  # the χ² tables wait behind "details"
    assert "track the payload in flight" in page.locator("#r-ambiguity").text_content()
    assert "q.boom" in page.locator("#where-summary").text_content() and "swing 70%" in page.locator("#where-summary").text_content()
    which = page.locator("#which").text_content()
    assert "93%" in which and "at its prior bound" in which and "at bound" in which and "55%" in which
    assert page.locator("#which tr.named").count() == 2
    assert "gap shrink 90%" in page.locator("#howfar").text_content() and "80%" in page.locator("#shares").text_content()
    assert "acts on impact" in page.locator("#gated").text_content()
    page.close()


def test_diagnosis_page_says_drifting_and_partly_consistent_in_plain_words(live, browser):  # noqa: F811
    """A drifting gap reads as drifting (not "no known effect explains it") and tells the operator not to
    adapt to it; an effect only partly consistent with the gap is named as not confirmed."""
    base, app = live
    where = {"gap": True, "carriers": ["q.boom"], "phases": {"swing": 1.0}, "noise": {"sigma": {"q.boom": 0.002}, "impact_sigma_m": 0.05},
             "channels": {"q.boom": {"chi2": 900.0, "dof": 300.0, "gap": True, "by_phase": {"swing": {"chi2": 900.0, "dof": 300.0}}}}}
    drifting = {"verdict": {"answer": "drifting", "effects": [], "partly_consistent": [],
                            "text": "drifting gap: the throws early and late in the log differ: q.boom changes from throw 14 on."},
                "where": where, "rounds": [], "plots": {}}
    partly = {"verdict": {"answer": "unexplained", "effects": ["valve_lag"], "confirmed": [],
                          "partly_consistent": [{"effect": "valve_lag", "why": ["leaves a gap in channels it changes (q.boom): its residual is not noise"]}],
                          "text": "unexplained, partly consistent with valve_lag"},
              "where": where, "rounds": [], "plots": {}}
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base)
    for report, expect, absent in ((drifting, ["not the same early and late", "throw 14", "do not adapt"], "no known effect explains it"),
                                   (partly, ["partly consistent with valve lag", "not confirmed", "its residual is not noise"], "behaves differently")):
        run_id = finished_diagnosis_run(app.state, "m1", report)
        page.goto(f"{base}/console/diagnosis.html#{run_id}")
        page.locator("#r-verdict", has_text=report["verdict"]["answer"]).wait_for(timeout=20_000)
        summary = page.locator("#r-summary").text_content()
        assert all(e in summary for e in expect) and absent not in summary, summary
    page.close()


def test_diagnosis_page_uploads_rosbags_and_shows_the_refusal(live, browser):  # noqa: F811
    """The rosbag2 upload form sends the bags, the mapping and the impacts as one multipart request
    (POST /api/diagnosis/uploads); an unusable upload is refused with the server's sentence."""
    base, _app = live
    page = browser.new_page(viewport={"width": 1440, "height": 900})
    log_in(page, base)
    page.goto(f"{base}/console/diagnosis.html")
    page.locator("#upload-fold summary").click()
    page.set_input_files("#up-bags", [{"name": "throw 1.mcap", "mimeType": "application/octet-stream", "buffer": b"\x89MCAP0\r\n"}])
    page.set_input_files("#up-mapping", [{"name": "map.toml", "mimeType": "text/plain", "buffer": b"[topics]\n"}])
    page.set_input_files("#up-impacts", [{"name": "impacts.csv", "mimeType": "text/csv",
                                          "buffer": b"throw_id,target_x_m,target_y_m,impact_x_m,impact_y_m\n"}])
    page.locator("#upload button[type=submit]").click()
    msg = page.locator("#upload-msg", has_text="the throw id")
    msg.wait_for(timeout=20_000)
    assert "409" not in msg.text_content() and "422" not in msg.text_content()  # a sentence, not a status code
    page.close()


def test_fleet_page_shows_the_lease_and_takes_a_machine_over_only_after_a_confirmation(live, browser, fake_runtime_factory):  # noqa: F811
    base, app = live
    rt = fake_runtime_factory(lease_holder="srv-other", undeliverable=2)  # the page loads once: no later info to wait for
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base)
    page.goto(f"{base}/console/fleet.html")
    row = "#fleet tbody tr[data-machine-id=m1]"
    page.locator(f"{row} td.lease", has_text="another server: srv-other").wait_for(timeout=20_000)
    assert page.locator(f"{row} td.undeliverable").inner_text() == "2"
    page.click(f"{row} button.take-over")
    page.locator("#confirm-dialog[open]").wait_for(timeout=10_000)
    assert page.evaluate("document.activeElement.id") == "confirm-cancel"  # Enter cancels
    page.keyboard.press("Enter")
    page.locator("#fleet-status", has_text="Takeover cancelled").wait_for(timeout=10_000)
    assert rt.lease_holder == "srv-other"
    page.click(f"{row} button.take-over")
    page.click("#confirm-ok")
    page.locator(f"{row} td.lease", has_text="this server").wait_for(timeout=20_000)
    assert rt.lease_holder == app.state.fleet.signer.server_id
    assert page.locator(f"{row} button.take-over").count() == 0


def _operator_on_the_fleet_page(base: str, app, browser, fake_runtime_factory):  # noqa: F811
    """A fake runtime m1 online and an operator logged in on the fleet page: (runtime, page)."""
    rt = fake_runtime_factory()
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    add_user(app.state.sessions, "op1", "operator-pass-1", "operator")
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    log_in(page, base, ("op1", "operator-pass-1"), start="/console/fleet.html")
    return rt, page


def test_a_console_past_its_log_in_still_stops_and_one_logged_out_says_the_stop_was_not_sent(live, browser, fake_runtime_factory):  # noqa: F811
    """docs/safety.md row S13: the console stays on its page. Its log-in expired: the E-STOP is sent and
    confirmed, the answer says the log-in expired. Its session ended (logged out elsewhere): the live
    stream ends and the banner says LOGGED OUT, the E-STOP is refused and the strip says NOT SENT
    with a local alarm (before: 401, and the page left for the log-in page without a word)."""
    from sqlalchemy import delete

    from server.db.models import AuthSession
    from tests.test_estop_expired_login import _expire

    base, app = live
    rt, page = _operator_on_the_fleet_page(base, app, browser, fake_runtime_factory)
    page.locator("#machine-state", has_text="READY").wait_for(timeout=20_000)
    token = next(c["value"] for c in page.context.cookies() if c["name"] == "slinger_session")

    _expire(app.state.sessions, token, 60.0)
    page.click("#estop")
    page.locator("#strip-msg", has_text="Your log-in expired at").wait_for(timeout=20_000)
    assert "confirmed by the runtime of m1" in page.inner_text("#strip-msg")
    assert rt.estop_reason is not None and "log-in expired" in rt.estop_reason
    # the runtime's published RuntimeInfo (latched) reaches the page (tests/conftest.py FakeRuntime)
    page.locator("#machine-state", has_text="E-STOPPED").wait_for(timeout=20_000)

    rt.estop_reason = None
    with app.state.sessions.begin() as db:  # logged out elsewhere
        db.execute(delete(AuthSession))
    page.locator("#server-banner", has_text="LOGGED OUT").wait_for(timeout=20_000)  # the stream ended, refused again
    page.keyboard.press("Escape")
    page.locator("#strip-msg", has_text="E-STOP NOT SENT to m1").wait_for(timeout=20_000)
    assert "Use the machine's own emergency stop now" in page.inner_text("#strip-msg")
    page.locator("#alarm-count", has_text="ALARMS 1").wait_for(timeout=10_000)
    assert "NOT SENT" in page.inner_text("#alarm-top")
    assert page.url.endswith("/console/fleet.html") and rt.estop_reason is None
    page.close()


def test_the_strip_announces_the_end_of_the_log_in_and_the_estop_outlives_it(settings, browser, fake_runtime_factory):  # noqa: F811
    """A 40 s log-in: the strip says when it ends (an alarm of the page, low, within 15 minutes of the
    end), then that it ended (medium); the E-STOP pressed after the end still stops the machine and
    says the log-in expired (docs/safety.md row S13); the page, loaded again, asks for a log-in."""
    settings.session_ttl_s = 40.0
    served = _serve(settings)
    base, app = next(served)
    try:
        rt, page = _operator_on_the_fleet_page(base, app, browser, fake_runtime_factory)
        page.locator("#alarm-top", has_text="LOW: Log-in ends at").wait_for(timeout=20_000)
        page.locator("#alarm-top", has_text="MEDIUM: Log-in ended at").wait_for(timeout=60_000)
        page.click("#estop")
        page.locator("#strip-msg", has_text="Your log-in expired at").wait_for(timeout=20_000)
        assert rt.estop_reason is not None and "log-in expired" in rt.estop_reason
        page.reload()  # anything but the stop asks for a new log-in
        page.wait_for_url("**/login.html**", timeout=20_000)
        page.close()
    finally:
        next(served, None)


def test_the_typed_aim_comes_back_after_a_new_log_in_as_an_edit_not_yet_set(live_3d, browser, fake_runtime_factory):  # noqa: F811
    """The log-in ends (logged out elsewhere) while the operator types a target on the console: the
    page leaves for the log-in page (Set, or a call of its own, answered 401), and after the new log-in
    the typed x, y and the mode (3D the second time) are back in the fields, not yet the target:
    Preview and Throw wait for Set, and Set aims there. The same after a reload under the LOGGED OUT
    banner. Before, the page came back with empty fields."""
    from sqlalchemy import delete

    from server.db.models import AuthSession

    base, app = live_3d
    fake_runtime_factory()
    wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
    add_user(app.state.sessions, "op1", "operator-pass-1", "operator")
    page = browser.new_page(viewport={"width": 1440, "height": 900})
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    log_in(page, base, ("op1", "operator-pass-1"), start="/console/")
    page.locator("#machine-state", has_text="READY").wait_for()
    page.wait_for_function("() => state.consoleId && state.machineId === 'm1'")

    def log_in_again():
        page.wait_for_url("**/login.html**")
        page.fill("#username", "op1")
        page.fill("#password", "operator-pass-1")
        page.click("#login")
        page.wait_for_url("**/console/**")
        page.locator("#status", has_text="Your aim from before the log-in is back in the fields").wait_for()

    def end_the_log_in_then(act):
        """Log out elsewhere; the page leaves for the log-in page by itself (a periodic call answered
        401) or shows LOGGED OUT (its live stream refused), and then ``act()`` takes it there."""
        with app.state.sessions.begin() as db:
            db.execute(delete(AuthSession))

        def settled() -> bool:
            if "login.html" in page.url:
                return True
            try:
                return page.locator("#server-banner", has_text="LOGGED OUT").is_visible()
            except Exception:  # the page is navigating
                return False

        wait_for(settled, 30, "LOGGED OUT or the log-in page")
        if "login.html" not in page.url:
            act()

    page.fill("#target-x", "8.75")
    page.fill("#target-y", "0")
    end_the_log_in_then(lambda: page.click("#target-set"))  # Set answered 401: to the log-in page
    log_in_again()
    assert (page.input_value("#target-x"), page.input_value("#target-y")) == ("8.75", "0")
    assert page.evaluate("state.editing && state.target === null")  # typed, not aimed at
    assert page.locator("#preview").is_disabled() and page.locator("#throw").is_disabled()
    page.click("#target-set")
    page.wait_for_function("() => !state.editing && state.target && Math.abs(state.target[0] - 8.75) < 1e-6")
    page.locator("#target", has_text="8.75 m from the turn axis").wait_for()

    page.check("input[name=mode][value='3d']")
    page.wait_for_function("() => state.mode === '3d'")
    page.fill("#target-x", "9.5")  # typed, never Set
    page.fill("#target-y", "1.5")
    end_the_log_in_then(page.reload)  # under the LOGGED OUT banner a reload asks for a log-in
    log_in_again()
    assert (page.input_value("#target-x"), page.input_value("#target-y")) == ("9.5", "1.5")
    assert page.evaluate("state.editing && state.target === null")
    assert page.evaluate("state.mode") == "3d" and page.is_checked("input[name=mode][value='3d']")  # the mode came back
    assert page.evaluate("fetch(`/api/consoles/${state.consoleId}`).then(r => r.json()).then(c => c.mode)") == "3d"
    assert page.evaluate("sessionStorage.getItem('slinger.console.aim')") is None  # put back once
    assert errors == [], errors
    page.close()
