"""No request body refuses an E-STOP (docs/safety.md row S14): the body's reason is optional and
the route reads it itself (server.fleet.routes.stop_reason). Before, a reason over 200 characters,
a reason that is not text or a body that is not JSON was answered 422 and the stop was not sent.

Runs the app in the test process against FakeRuntime (tests/conftest.py) over loopback Zenoh.
"""

from __future__ import annotations

import pytest

from runtime.protocol.messages import ABORT_REASON_CHARS
from server.fleet.routes import stop_reason
from tests.conftest import add_user, login, wait_for


@pytest.mark.parametrize(("raw", "expected"), [
    (b"", "operator abort"),
    (b'{"reason": "  "}', "operator abort"),
    (b'{"reason": "drill"}', "drill"),
    (b'{"reason": "' + b"x" * 300 + b'"}', "x" * (ABORT_REASON_CHARS - 1) + "\u2026"),
    (b'{"reason": "bell\\u0007"}', "bell\\x07"),
    (b"{not json", "operator abort (request body not read: not JSON)"),
    (b"\xff\xfe", "operator abort (request body not read: not JSON)"),
    (b'{"reason": 5}', "operator abort (request body not read: no text reason)"),
    (b'["stop"]', "operator abort (request body not read: no text reason)"),
])
def test_the_stop_reason_of_any_body(raw, expected):
    assert stop_reason(raw) == expected


def test_a_bad_body_still_stops_the_machine(client, fake_runtime_factory):
    add_user(client.app.state.sessions, "op1", "operator-pass-1", "operator")
    login(client, "op1", "operator-pass-1")
    rt = fake_runtime_factory()
    wait_for(lambda: client.app.state.fleet.is_online("m1"), 20, "m1 online")
    bodies = [{"json": {"reason": "y" * 300}}, {"content": b"{not json", "headers": {"content-type": "application/json"}},
              {"json": {"reason": 5}}, {"json": ["a"]}, {}]
    for kw in bodies:
        rt.estop_reason = None
        r = client.post("/api/machines/m1/estop", **kw)
        assert r.status_code == 200, (kw, r.text)
        assert rt.estop_reason is not None and rt.estop_reason.endswith("(op1)"), rt.estop_reason
    assert client.post("/api/machines/m1/abort", content=b"\x00\x01").status_code == 200  # the alias too
    spec = client.get("/openapi.json").json()["paths"]["/api/machines/{machine_id}/estop"]["post"]
    assert spec["requestBody"]["content"]["application/json"]["schema"]["properties"]["reason"]["maxLength"] == 200
