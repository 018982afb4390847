"""An E-STOP with a token the session mirror does not hold never delays another E-STOP
(docs/safety.md row S15).

The E-STOP is an async route served on the event loop. Before, a token the mirror did not hold (a
logged-out console pressing its E-STOP, a stranger's guess) was looked up in the database on that
loop: with the database locked, for its busy timeout, and every other stop waited behind it. Now
that lookup runs in a worker thread. Here the lookup of unknown tokens is slowed to 8 s (as a
locked database would) and an operator's E-STOP, pressed while one such lookup is under way, is
answered before it ends.

Runs the app under uvicorn in a thread of the test process against FakeRuntime (tests/conftest.py).
"""

from __future__ import annotations

import threading
import time

import httpx

from tests.conftest import add_user, wait_for
from tests.test_browser_pages import _serve

SLOW_LOOKUP_S = 8.0


def test_an_unknown_tokens_lookup_does_not_hold_an_operators_stop(settings, fake_runtime_factory, monkeypatch):
    import server.api.deps as deps

    served = _serve(settings)
    base, app = next(served)
    try:
        add_user(app.state.sessions, "op1", "operator-pass-1", "operator")
        rt = fake_runtime_factory()
        wait_for(lambda: app.state.fleet.is_online("m1"), 20, "m1 online")
        with httpx.Client(base_url=base, timeout=30) as op:
            assert op.post("/api/auth/login", json={"username": "op1", "password": "operator-pass-1"}).status_code == 200
            looked_up = threading.Event()
            real = deps.session_for_token

            def slow_lookup(db, token, grace_s=0.0):  # a locked database: the read waits for its busy timeout
                if token == "not-a-session":
                    looked_up.set()
                    time.sleep(SLOW_LOOKUP_S)
                return real(db, token, grace_s)

            monkeypatch.setattr(deps, "session_for_token", slow_lookup)
            stranger: dict = {}

            def press_with_an_unknown_token() -> None:
                r = httpx.post(f"{base}/api/machines/m1/estop", headers={"Authorization": "Bearer not-a-session"}, timeout=30)
                stranger.update(status=r.status_code, done=time.monotonic())

            th = threading.Thread(target=press_with_an_unknown_token)
            th.start()
            assert looked_up.wait(10), "the unknown token was never looked up"
            r = op.post("/api/machines/m1/estop", json={"reason": "while a lookup waits"})
            answered = time.monotonic()
            assert r.status_code == 200, r.text
            assert rt.estop_reason is not None and "while a lookup waits" in rt.estop_reason
            th.join(SLOW_LOOKUP_S + 10)
            assert stranger["status"] == 401
            assert answered < stranger["done"], "the operator's stop waited for the stranger's lookup"
    finally:
        next(served, None)
