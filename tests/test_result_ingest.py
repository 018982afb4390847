"""The result store's ingest path (server.fleet.results.ResultStore): telemetry staged to a unique
temporary file (as the fleet link does off its database thread) is renamed into place only for
an accepted result, in the transaction that stores the row; refused results (never issued, not
matching the issued throw, bad base64) leave no file and never replace a throw's telemetry."""

from __future__ import annotations

import base64

import pytest

from runtime.protocol.messages import ThrowResult
from server.db.migrate import upgrade
from server.db.models import Machine, Throw
from server.db.session import make_engine, make_sessionmaker
from server.fleet.results import ResultStore, UnknownThrow


@pytest.fixture
def store(tmp_path):
    url = f"sqlite:///{tmp_path / 's.db'}"
    upgrade(url)
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    with sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.flush()
        db.add_all([Throw(id=t, machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=0.0, target_z_m=0.0,
                          status="released") for t in ("t1", "t2")])
    yield ResultStore(sessions, tmp_path / "var")
    engine.dispose()


def _result(throw_id: str, telemetry: bytes | str | None, target=(8.0, 0.0, 0.0)) -> ThrowResult:
    b64 = telemetry if isinstance(telemetry, str) else (base64.b64encode(telemetry).decode() if telemetry else None)
    return ThrowResult(machine_id="m1", stamp_s=1.0, throw_id=throw_id, mode="2d", status="landed",
                       target_m=list(target), impact_m=[8.1, 0.05, 0.0], policy_version="p", duration_s=2.0,
                       telemetry_mcap_b64=b64)


def test_staged_telemetry_is_placed_only_for_accepted_results(store):
    tel = store.data_dir / "telemetry"
    staged = [store.stage_telemetry(r) for r in (_result("t1", b"genuine"), _result("ghost", b"forged"))]
    assert all(p is not None and p.is_file() and p.name.endswith(".tmp") for p in staged)
    out = store.store_results([_result("t1", b"genuine"), _result("ghost", b"forged")], staged)
    assert isinstance(out[0], Throw) and out[0].status == "landed" and isinstance(out[1], UnknownThrow)
    assert (tel / "t1.mcap").read_bytes() == b"genuine" and not (tel / "ghost.mcap").exists()
    # a result for an issued id that does not match the issued throw: refused, the file stays
    out = store.store_results([_result("t1", b"forged", target=(9.0, 0.0, 0.0))])
    assert isinstance(out[0], UnknownThrow) and "does not match" in str(out[0])
    assert (tel / "t1.mcap").read_bytes() == b"genuine"
    # re-delivered: same row, same file
    out = store.store_results([_result("t1", b"genuine")])
    assert isinstance(out[0], Throw) and (tel / "t1.mcap").read_bytes() == b"genuine"
    assert sorted(p.name for p in tel.iterdir()) == ["t1.mcap"]  # no temporary file left


def test_bad_telemetry_is_refused_per_result(store):
    with pytest.raises(ValueError):
        store.stage_telemetry(_result("t2", "not base64!"))
    out = store.store_results([_result("t2", "not base64!"), _result("t1", None)])
    assert isinstance(out[0], ValueError) and isinstance(out[1], Throw) and out[1].telemetry_path is None
    with pytest.raises(ValueError):
        store.store_result(_result("t2", "%%%"))
    assert not (store.data_dir / "telemetry" / "t2.mcap").exists()
    assert list(store.data_dir.rglob("*.tmp")) == []
