"""One writer per machine, enforced by the machine (runtime.service's lease): a runtime obeys one
server at a time, refuses another's commands with a reason that server can show, lets the lease
expire only after its holder's silence (never during its throw) or go by a signed takeover, and
tags each result with the server that issued the throw; the outbox delivers it to every server's
queryable so the issuing one stores it (runtime.outbox.zenoh_deliverer)."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from runtime.command_auth import CommandVerifier, sign, verify_mac, write_key
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.outbox import DeliveryRefused, Outbox, zenoh_deliverer
from runtime.policy import PolicyRunner
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    EstopReset,
    EstopResetAck,
    LeaseAck,
    LeaseRequest,
    ResultAck,
    ReturnToReady,
    ReturnToReadyAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    decode,
    encode,
)
from runtime.service import LEASE_S, RuntimeService
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from runtime.zenoh_session import open_session
from server.fleet.command_signer import SERVER_ID_ENV, CommandSigner, default_server_id
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from tests.conftest import free_port, wait_for
from tests.fixtures import write_test_policy

KEY = bytes(range(32))
EPOCH = 1_700_000_000_000
TARGET = [8.0, ARM_PLANE_OFFSET_M, 0.0]


@pytest.fixture(scope="module")
def holding_path(tmp_path_factory) -> Path:
    return write_test_policy(tmp_path_factory.mktemp("hold"), "2d", name="hold", release_after_bias=-2.0)


class Machine:
    """RuntimeService (fake clock) fed by a twin machine's states, 10 ms per tick."""

    def __init__(self, policy: Path):
        self.now = [100.0]
        self.results: list[ThrowResult] = []
        ex = ThrowExecutor({"2d": PolicyRunner.load(policy)}, config=ExecutorConfig(release_check_radius_m=None))
        self.service = RuntimeService("m1", ex, lambda k, d: None, self.results.append,
                                      verifier=CommandVerifier(KEY, EPOCH, window_s=600.0), clock=lambda: self.now[0])  # freshness: not judged here (a loaded host)
        self.twin = TwinMachine(SimulatedMachine(seed=1), "m1", clock=lambda: self.now[0])

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.service.on_state(encode(self.twin.state()))
            self.now[0] += 0.01

    def wait(self, seconds: float) -> None:
        """Time passes with the machine at rest (states keep coming)."""
        self.tick(int(round(seconds / 0.01)))


def _signed(msg, server: str | None) -> bytes:
    return encode(sign(msg, KEY, "op", EPOCH, server=server))


def _throw(m: Machine, throw_id: str, server: str | None) -> ThrowAck:
    req = ThrowRequest(throw_id=throw_id, machine_id="m1", mode="2d", target_m=TARGET)
    return decode(ThrowAck, m.service.handle_throw(_signed(req, server)))


def _lease(m: Machine, server: str, takeover: bool = False) -> LeaseAck:
    return decode(LeaseAck, m.service.handle_lease(_signed(LeaseRequest(machine_id="m1", takeover=takeover), server)))


def test_one_server_commands_the_machine_another_is_refused_with_the_reason(holding_path):
    m = Machine(holding_path)
    m.tick()
    assert _throw(m, "a1", "srv-a").accepted
    assert m.service.info().lease_holder == "srv-a"
    refused = _throw(m, "b1", "srv-b")
    assert not refused.accepted and refused.reason.startswith("machine m1 is commanded by server srv-a: another server's commands are refused")
    reset = decode(EstopResetAck, m.service.handle_estop_reset(_signed(EstopReset(machine_id="m1"), "srv-b")))
    assert not reset.reset and "commanded by server srv-a" in reset.reason
    back = decode(ReturnToReadyAck, m.service.handle_return_to_ready(_signed(ReturnToReady(machine_id="m1"), "srv-b")))
    assert not back.accepted and "commanded by server srv-a" in back.reason
    ask = _lease(m, "srv-b")
    assert not ask.granted and ask.holder == "srv-a" and "commanded by server srv-a" in ask.reason
    # an E-STOP is never refused: any server (or none) stops the machine
    stop = decode(AbortAck, m.service.handle_abort(_signed_abort("srv-b")))
    assert stop.aborted_throw_id == "a1" and m.service.info().estop_latched
    assert m.results[-1].server_id == "srv-a" and verify_mac(m.results[-1], KEY) is None  # the result is a's
    assert decode(EstopResetAck, m.service.handle_estop_reset(_signed(EstopReset(machine_id="m1"), "srv-a"))).reset


def _signed_abort(server: str) -> bytes:
    from runtime.protocol.messages import AbortRequest

    return _signed(AbortRequest(machine_id="m1", reason="b's stop"), server)


def test_the_lease_expires_after_the_holders_silence_never_during_its_throw(holding_path):
    m = Machine(holding_path)
    m.tick()
    assert _throw(m, "a1", "srv-a").accepted
    m.wait(LEASE_S + 2)  # a's throw still runs (a holding policy, no release yet... it fails at 10 s)
    assert m.results and m.results[-1].throw_id == "a1"  # it ended (no release within 10 s)
    m.service.handle_abort(b"")  # stop the arm, then reset by a (renews a's lease)
    assert decode(EstopResetAck, m.service.handle_estop_reset(_signed(EstopReset(machine_id="m1"), "srv-a"))).reset
    m.wait(LEASE_S - 1)
    assert not _lease(m, "srv-b").granted  # a spoke 29 s ago
    m.wait(2)
    granted = _lease(m, "srv-b")  # a silent for 31 s: b may command
    assert granted.granted and granted.holder == "srv-b" and granted.expires_in_s == pytest.approx(LEASE_S)
    assert m.service.info().lease_holder == "srv-b"
    assert "commanded by server srv-b" in _throw(m, "a2", "srv-a").reason


def test_a_deliberate_signed_takeover_and_never_during_a_throw(holding_path):
    m = Machine(holding_path)
    m.tick()
    assert _throw(m, "a1", "srv-a").accepted
    m.tick(20)
    taken = _lease(m, "srv-b", takeover=True)
    assert not taken.granted and taken.reason == "takeover refused: throw a1 of server srv-a runs"
    m.service.handle_abort(b"")
    m.service.handle_estop_reset(_signed(EstopReset(machine_id="m1"), "srv-a"))
    unsigned = decode(LeaseAck, m.service.handle_lease(encode(LeaseRequest(machine_id="m1", takeover=True))))
    assert not unsigned.granted and unsigned.reason == "unsigned" and unsigned.holder == "srv-a"
    taken = _lease(m, "srv-b", takeover=True)
    assert taken.granted and taken.holder == "srv-b"
    published = m.service.info()
    assert isinstance(published, RuntimeInfo) and published.lease_holder == "srv-b"


def test_the_server_names_itself_in_what_it_signs(tmp_path, monkeypatch):
    monkeypatch.delenv(SERVER_ID_ENV, raising=False)
    for site in (tmp_path / "a", tmp_path / "b"):
        write_key(site / "machines" / "m1" / "command.key", KEY)
    a, b = CommandSigner(tmp_path / "a"), CommandSigner(tmp_path / "b")
    assert a.server_id != b.server_id and a.server_id == default_server_id(tmp_path / "a")  # stable per site copy
    signed = a.sign(ThrowRequest(throw_id="t", machine_id="m1", mode="2d", target_m=TARGET), "m1", "op", EPOCH)
    assert signed.auth.server == a.server_id and verify_mac(signed, KEY) is None
    forged = signed.model_copy(update={"auth": signed.auth.model_copy(update={"server": "other"})})
    assert verify_mac(forged, KEY) == "bad signature"  # the name is covered by the MAC
    monkeypatch.setenv(SERVER_ID_ENV, "console-2")
    assert CommandSigner(tmp_path / "a").server_id == "console-2"
    monkeypatch.setenv(SERVER_ID_ENV, "bad id!")
    with pytest.raises(ValueError, match=SERVER_ID_ENV):
        CommandSigner(tmp_path / "a")


def test_results_reach_the_issuing_server_beside_a_refusing_one(tmp_path):
    """Two servers answer keys.THROW_RESULT (as two servers of one site do): the one that did not
    issue the throws refuses them. Every result is stored by the issuing one, none is retried on."""
    ends = [f"tcp/127.0.0.1:{free_port()}" for _ in range(2)]
    stored: list[str] = []

    def issuer(query):
        res = decode(ThrowResult, query.payload.to_bytes())
        assert res.server_id == "srv-a"
        stored.append(res.throw_id)
        query.reply(keys.THROW_RESULT, encode(ResultAck(throw_id=res.throw_id, stored=True)))

    def stranger(query):
        res = decode(ThrowResult, query.payload.to_bytes())
        query.reply_err(f"result of throw {res.throw_id!r} refused: not a throw this server issued".encode())

    with open_session(listen=[ends[0]]) as a, open_session(listen=[ends[1]]) as b, open_session(connect=ends) as rt:
        queryables = [b.declare_queryable(keys.THROW_RESULT, stranger, complete=True),
                      a.declare_queryable(keys.THROW_RESULT, issuer, complete=True)]
        probe = ThrowResult(machine_id="m1", stamp_s=0.5, throw_id="probe", mode="2d", status="failed", target_m=TARGET,
                            duration_s=1.0, server_id="srv-a")
        deliver = zenoh_deliverer(rt, timeout_s=2.0)

        def reached() -> bool:
            try:
                return deliver(encode(probe)) is not None
            except DeliveryRefused:
                return False  # only the stranger's link is up yet

        wait_for(reached, 20, "the issuing server reachable")
        box = Outbox(tmp_path / "outbox", deliver, reserve_bytes=0)
        for i in range(8):
            box.put(probe.model_copy(update={"throw_id": f"t{i}", "stamp_s": 1.0 + i}))
        assert box.deliver_pending() == 8 and box.pending() == [] and box.undeliverable == 0
        assert set(stored) >= {f"t{i}" for i in range(8)}
        for q in queryables:
            q.undeclare()
        time.sleep(0.2)


def test_a_second_server_takes_over_deliberately_through_its_fleet_link(tmp_path, holding_path):
    """server.fleet.commands.FleetCommands.lease over Zenoh: server b's throw is refused while a
    holds the lease, b's signed takeover moves it, then a is refused with b named."""
    from server.fleet.commands import FleetCommands

    m = Machine(holding_path)
    m.tick()
    site = tmp_path / "site"
    write_key(site / "machines" / "m1" / "command.key", KEY)

    class Link(FleetCommands):
        def __init__(self, session, server_id):
            self.session, self.signer, self.query_timeout_s = session, CommandSigner(site, server_id), 5.0
            self._estop = SimpleNamespace(latch=lambda machine_id: None)  # no E-STOP held by this server

        def is_online(self, machine_id):
            return True

        def cached_info(self, machine_id):
            return m.service.info()

        def forget_info(self, machine_id):
            pass

        def clock_offset_s(self, machine_id):
            return 0.0

        def _note_info(self, info, published):
            pass

    end = f"tcp/127.0.0.1:{free_port()}"
    with open_session(listen=[end]) as rt, open_session(connect=[end]) as sa, open_session(connect=[end]) as sb:
        qs = [rt.declare_queryable(keys.throw("m1"), lambda q: q.reply(q.key_expr, m.service.handle_throw(q.payload.to_bytes()))),
              rt.declare_queryable(keys.lease("m1"), lambda q: q.reply(q.key_expr, m.service.handle_lease(q.payload.to_bytes())))]
        a, b = Link(sa, "srv-a"), Link(sb, "srv-b")
        wait_for(lambda: _reachable(a), 20, "the runtime's queryables")
        assert a.lease("m1", "alice").granted
        ack, _ = b.request_throw(ThrowRequest(throw_id="b1", machine_id="m1", mode="2d", target_m=TARGET), "bob")
        assert not ack.accepted and "commanded by server srv-a" in ack.reason
        taken = b.lease("m1", "bob", takeover=True)
        assert taken.granted and taken.holder == "srv-b"
        ack, _ = a.request_throw(ThrowRequest(throw_id="a1", machine_id="m1", mode="2d", target_m=TARGET), "alice")
        assert not ack.accepted and "commanded by server srv-b" in ack.reason
        for q in qs:
            q.undeclare()


def _reachable(link) -> bool:
    from server.fleet.commands import RuntimeUnavailable

    try:
        link.lease("m1", "probe")
        return True
    except RuntimeUnavailable:
        return False


def test_the_machine_answer_names_the_lease_holder_and_undeliverable_results_and_an_operator_takes_over(
        client, fake_runtime_factory):
    """GET /api/machines shows whose commands the runtime obeys (its lease holder, and whether that
    is this server) and how many results its outbox set aside; POST .../lease/takeover takes the
    lease with a signed LeaseRequest(takeover=True) in the operator's name, audited."""
    from tests.conftest import add_user, login

    def machine() -> dict:
        r = client.get("/api/machines")
        assert r.status_code == 200, r.text
        return next(m for m in r.json() if m["id"] == "m1")

    rt = fake_runtime_factory(lease_holder="srv-other", undeliverable=3)
    m = wait_for(lambda: (m := machine())["online"] and m["lease_holder"] and m, 20, "m1 online with its lease")
    assert (m["lease_holder"], m["lease_held_here"], m["undeliverable_results"]) == ("srv-other", False, 3), m
    r = client.post("/api/machines/m1/lease/takeover")
    here = client.app.state.fleet.signer.server_id
    assert r.status_code == 200 and r.json() == {"machine_id": "m1", "granted": True, "holder": here, "reason": None}, r.text
    assert rt.lease_holder == here
    m = machine()  # the takeover dropped the cached info: the runtime is asked again
    assert (m["lease_holder"], m["lease_held_here"]) == (here, True), m
    entry = client.get("/api/audit", params={"action": "lease_takeover"}).json()[0]
    assert entry["subject"] == "m1" and entry["detail"]["granted"] is True and entry["detail"]["holder"] == here
    rt.lease_holder = None
    client.app.state.fleet.forget_info("m1")
    m = machine()
    assert (m["lease_holder"], m["lease_held_here"]) == (None, None), m  # nobody holds it
    add_user(client.app.state.sessions, "vic", "viewer-pass-1", "viewer")
    login(client, "vic", "viewer-pass-1")
    assert client.post("/api/machines/m1/lease/takeover").status_code == 403
    assert rt.lease_holder is None


@pytest.mark.system
def test_two_servers_show_who_commands_the_machine_and_the_other_takes_it_over(settings, zenoh_endpoint, tmp_path,
                                                                              monkeypatch, fake_runtime_factory):
    """Two servers of one site (two apps, their own data and server ids, one Zenoh network with b a
    client of a's endpoint, the site's keys; the runtime: tests.conftest.FakeRuntime's lease): each
    machine answer says which of them the runtime obeys; server b's operator takes the machine over,
    and then a's answer names b."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from tests.conftest import ADMIN, add_user, login

    def started(server_id: str, s):
        monkeypatch.setenv(SERVER_ID_ENV, server_id)
        c = TestClient(create_app(s))
        c.__enter__()
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        return c

    def machine(c) -> dict:
        r = c.get("/api/machines")
        assert r.status_code == 200, r.text
        return next((m for m in r.json() if m["id"] == "m1"), {"online": False})

    b_settings = settings.model_copy(update={"data_dir": tmp_path / "b", "database_url": f"sqlite:///{tmp_path / 'b' / 'slinger.db'}",
                                             "zenoh_mode": "client", "zenoh_listen": [], "zenoh_connect": [zenoh_endpoint],
                                             "site_dir": settings.resolved_site_dir})
    a = started("srv-a", settings)
    try:
        rt = fake_runtime_factory()
        b = started("srv-b", b_settings)
        try:
            wait_for(lambda: machine(a)["online"] and machine(b)["online"], 20, "m1 online at both servers")
            assert a.post("/api/machines/m1/lease/takeover").json()["holder"] == "srv-a"
            b.app.state.fleet.forget_info("m1")
            mb = machine(b)
            assert (mb["lease_holder"], mb["lease_held_here"]) == ("srv-a", False), mb
            r = b.post("/api/machines/m1/lease/takeover")
            assert r.status_code == 200 and r.json()["holder"] == "srv-b", r.text
            a.app.state.fleet.forget_info("m1")
            ma, mb = machine(a), machine(b)
            assert (ma["lease_holder"], ma["lease_held_here"]) == ("srv-b", False), ma
            assert (mb["lease_holder"], mb["lease_held_here"]) == ("srv-b", True), mb
            assert rt.lease_holder == "srv-b"
        finally:
            b.__exit__(None, None, None)
    finally:
        a.__exit__(None, None, None)
