"""schemathesis over the OpenAPI as an admin and as a viewer: no operation answers a server error
(5xx), and every answer's status is documented and its body matches the documented schema
(schemathesis' status-code and response-schema conformance checks).

Bounded for CI: a fixed seed, deterministic generation, a few fuzzed examples per operation
(``MAX_EXAMPLES``) plus schemathesis's coverage phase (boundary and invalid values of every
parameter), no stateful phase. The app runs in-process (ASGI) with SQLite, no 3D view and no
machine online, so no generated request can move a machine. Excluded (see EXCLUDED):

- POST /api/auth/logout: it would end the admin session the other requests use.
- POST /api/machines/{machine_id}/abort, /estop and /estop/reset: each waits the Zenoh query
  timeout for a runtime that is not there (1 s per example here; stops are the subject of the
  fault-injection suite).
- POST /api/machines/{machine_id}/return-to-ready: would move a machine; with no runtime online it
  answers 503 by design (as estop/reset); test_return_to_ready.py and the browser test cover it.
- POST /api/throws: would command a machine; the throw path is covered with fake and real
  runtimes in test_api.py / test_stack.py.
- POST /api/jobs: a probe job runs in-process here (no workers) for up to steps x step_s =
  1000 x 10 s; test_jobs.py covers it.
- GET /api/diagnosis/effects: builds the effects catalogue in-process (no worker here), over
  schemathesis's 10 s read timeout on a loaded machine; it takes no parameters. (This test found
  its 500: job kind "catalog" missing from JOB_KINDS, fixed by migration 0005, kept fixed by
  test_jobs.py::test_every_job_runner_is_an_allowed_kind.)
- GET /api/live: the live-push event stream never ends by design (test_live.py and the browser
  tests cover it).
"""

from __future__ import annotations

import pytest
import schemathesis
from schemathesis.config import SchemathesisConfig
from schemathesis.checks import not_a_server_error, response_schema_conformance, status_code_conformance

from tests.conftest import ADMIN, add_user, free_port

MAX_EXAMPLES = 5
SEED = 20261121
EXCLUDED = [("POST", r"^/api/auth/logout$"), ("POST", r"^/api/machines/[^/]+/abort$"),
            ("POST", r"estop"), ("POST", r"return-to-ready$"), ("POST", r"^/api/throws$"), ("POST", r"^/api/jobs$"),
            ("GET", r"^/api/diagnosis/effects$"), ("GET", r"^/api/live$")]

CONFIG = SchemathesisConfig.from_str(f"""
seed = {SEED}
suppress-health-check = ["all"]
[generation]
max-examples = {MAX_EXAMPLES}
deterministic = true
database = "none"
[phases.stateful]
enabled = false
""")


class StartedApp:
    """The app of the ``client`` fixture, whose lifespan already ran: schemathesis's ASGI client
    starts a lifespan per call, this answers it without running the app's again."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "lifespan":
            return await self.app(scope, receive, send)
        while True:
            message = await receive()
            kind = message["type"].rsplit(".", 1)[-1]  # startup / shutdown
            await send({"type": f"lifespan.{kind}.complete"})
            if kind == "shutdown":
                return


def _load_schema():
    """The OpenAPI schema of an app built from default settings (building it does no I/O; the
    schema does not depend on settings). Requests then go to the ``client`` fixture's app.
    (Loaded at import: schemathesis's lazy ``from_fixture`` does not work with pytest 9.)"""
    from server.app import create_app
    from server.config import Settings

    loaded = schemathesis.openapi.from_asgi("/openapi.json", StartedApp(create_app(Settings(viser_enabled=False))),
                                            config=CONFIG)
    for method, path in EXCLUDED:
        loaded = loaded.exclude(method=method, path_regex=path)
    return loaded


schema = _load_schema()


@pytest.fixture(scope="module")
def running(tmp_path_factory):
    """(the app, started once for all operations, {user name: token} of an admin and a viewer)."""
    from argon2 import PasswordHasher
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("schemathesis") / "var", viser_enabled=False,
                        zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"], query_timeout_s=1.0, auto_migrate=True)
    cheap = PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1)  # argon2's cost is not under test
    with pytest.MonkeyPatch.context() as mp, TestClient(create_app(settings)) as c:
        mp.setattr("server.auth._hasher", cheap)
        add_user(c.app.state.sessions, *ADMIN, "admin")
        add_user(c.app.state.sessions, "vera", "viewer-pass-1", "viewer")
        tokens = {name: c.post("/api/auth/login", json={"username": name, "password": pw}).json()["token"]
                  for name, pw in (ADMIN, ("vera", "viewer-pass-1"))}
        yield StartedApp(c.app), tokens


CHECKS = [not_a_server_error, status_code_conformance, response_schema_conformance]


@schema.parametrize()
def test_no_server_errors_and_conformance_as_admin(case, running):
    app, tokens = running
    case.call_and_validate(app=app, headers={"Authorization": f"Bearer {tokens[ADMIN[0]]}"}, checks=CHECKS)


@schema.parametrize()
def test_no_server_errors_and_conformance_as_viewer(case, running):
    app, tokens = running
    case.call_and_validate(app=app, headers={"Authorization": f"Bearer {tokens['vera']}"}, checks=CHECKS)
