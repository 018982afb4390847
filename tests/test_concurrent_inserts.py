"""Rows that two writers may add at once. A machine's row and its runtime's policy versions are
added on first sighting by whichever writer sees it first: the fleet's thread (runtime info) or
an API request (a throw, a policy offer). Two first sightings at once must both commit and leave
one row (a SELECT-then-add lets both see no row and fails the second commit on the unique key);
two uploads of one policy file, or two adds of one account name, at once give one row and a
clear conflict, not a server error. On SQLite and PostgreSQL."""

from __future__ import annotations

import threading

import pytest
from sqlalchemy import select

from runtime.protocol.messages import PolicyInfo
from server.accounts.auth import UserExists, create_user
from server.db.migrate import upgrade
from server.db.models import AuditEntry, Machine, PolicyVersion, Throw, User
from server.db.session import make_engine, make_sessionmaker
from server.db.upsert import insert_if_absent
from server.errors import Conflict
from server.policies.versions import PolicyService
from server.fleet.results import ResultStore, ensure_machine

SHA = "c" * 64


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def sessions(request, tmp_path):
    url = f"sqlite:///{tmp_path / 'rows.db'}" if request.param == "sqlite" else request.getfixturevalue("pg_url")
    upgrade(url)
    engine = make_engine(url)
    yield make_sessionmaker(engine)
    engine.dispose()


MANIFEST = {"name": "v1", "mode": "2d", "onnx_sha256": SHA}


def _writer_a(sessions, add) -> threading.Thread:
    """Writer A, started: ``add(db)`` inside a transaction that it holds open (uncommitted) for
    0.5 s before committing; returns once A's rows are flushed, so the caller's statements run
    against them."""
    held = threading.Event()

    def run() -> None:
        with sessions.begin() as db:
            add(db)
            db.flush()
            held.set()
            threading.Event().wait(0.5)

    a = threading.Thread(target=run)
    a.start()
    assert held.wait(10), "writer A did not flush"
    return a


def _add_version(db) -> None:
    db.add(PolicyVersion(name="v1", mode="2d", sha256=SHA, manifest={}))


@pytest.mark.parametrize("writer", ["runtime info", "policy registration"])
def test_two_first_sightings_at_once_both_commit_one_row(sessions, tmp_path, writer):
    """Writer A adds m1 and its policy version (as its runtime reports it: no manifest) and holds
    its transaction open; writer B starts meanwhile: the fleet's upsert of the same runtime's
    info, or ``slinger up`` registering the deployed policy. B waits for A, then commits without
    error; one machine row (still marked simulated: B's False does not clear it) and one policy
    version remain, with the registration's manifest where B registered it."""
    def add(db) -> None:
        ensure_machine(db, "m1", simulated=True)
        _add_version(db)

    a = _writer_a(sessions, add)  # B's statements run now, against A's uncommitted rows
    store = ResultStore(sessions, tmp_path)
    if writer == "runtime info":
        store.upsert_machine("m1", False, [PolicyInfo(mode="2d", version="v1", sha256=SHA)])
    else:
        store.register_policy(MANIFEST)
    a.join(30)
    with sessions() as db:
        machines = db.scalars(select(Machine)).all()
        assert [(m.id, m.simulated) for m in machines] == [("m1", True)]
        assert machines[0].last_seen_at >= machines[0].first_seen_at
        assert [(p.sha256, p.manifest) for p in db.scalars(select(PolicyVersion)).all()] == [
            (SHA, MANIFEST if writer == "policy registration" else {})]


def test_ensure_machine_refreshes_a_known_row_and_a_throw_can_reference_it(sessions):
    with sessions.begin() as db:
        first = ensure_machine(db, "m2", simulated=False)
        seen = first.last_seen_at
    with sessions.begin() as db:
        again = ensure_machine(db, "m2", simulated=True)
        assert again.simulated is True and again.last_seen_at >= seen
        db.add(Throw(id="t1", machine_id="m2", mode="2d", status="requested", target_x_m=8.0, target_y_m=0.0,
                     target_z_m=0.0, requested_by="test"))
    with sessions() as db:
        assert db.get(Throw, "t1").machine_id == "m2"
        assert insert_if_absent(db, Machine, ["id"], id="m2", simulated=False) is False
        assert insert_if_absent(db, Machine, ["id"], id="m3", simulated=False) is True
        db.rollback()


def test_an_upload_racing_another_of_the_same_file_is_a_conflict(sessions, tmp_path):
    """B uploads (``PolicyService.add_version``) while A's insert of the same file is uncommitted:
    B's early check sees nothing, then its insert waits for A and B answers Conflict (409), not
    an integrity error (500). Afterwards one version; a second upload is refused before any write;
    a fresh file is added with its audit entry."""
    policies = PolicyService(None, sessions, ResultStore(sessions, tmp_path / "var"), settings=None, jobs=None)
    onnx = tmp_path / "p.onnx"
    onnx.write_bytes(b"policy bytes")
    a = _writer_a(sessions, _add_version)
    with pytest.raises(Conflict, match="already a policy version"):
        policies.add_version(MANIFEST, onnx, "op", evaluate=False)
    a.join(30)
    with pytest.raises(Conflict, match="already a policy version"):
        policies.add_version(MANIFEST, onnx, "op", evaluate=False)
    row = policies.add_version({**MANIFEST, "name": "v2", "onnx_sha256": "d" * 64}, onnx, "op", evaluate=False)
    with sessions() as db:
        assert sorted(p.name for p in db.scalars(select(PolicyVersion))) == ["v1", "v2"]
        assert [(e.action, e.subject) for e in db.scalars(select(AuditEntry))] == [("policy_upload", str(row.id))]


def test_an_account_added_twice_at_once_is_refused_as_taken(sessions):
    """B adds the name while A's add of it is uncommitted: B waits, then is refused (UserExists,
    the API's 409); A's account stands. An account added alone gets its defaults (a session key)."""
    a = _writer_a(sessions, lambda db: create_user(db, "ops", "a long enough password", "operator"))
    with pytest.raises(UserExists, match="'ops' exists"), sessions.begin() as db:
        create_user(db, "ops", "another long password", "viewer")
    a.join(30)
    with sessions.begin() as db:
        alone = create_user(db, "ops2", "a long enough password", "viewer")
        assert alone.id is not None and len(alone.session_key) == 64
    with sessions() as db:
        assert [(u.username, u.role) for u in db.scalars(select(User).order_by(User.username))] == [
            ("ops", "operator"), ("ops2", "viewer")]
