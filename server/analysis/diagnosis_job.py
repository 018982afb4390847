"""The ``diagnosis`` job's body (worker side): export a machine's newest landed throws with
telemetry as a dataset (sim_twin.diagnosis.dataset format), or convert an uploaded set of rosbag2
bags into one (sim_twin.diagnosis.rosbag, server.analysis.diagnosis_upload), and diagnose it.

Files go under the job's folder (server.jobs.specs.job_dir)::

    dataset/      index.json + throws/*.mcap
    report/       report.json, profile_fitted.json, where.png, which.png, how_far.png

Status, progress, error and the verdict live in the job's row only (server.jobs.store).
"""

from __future__ import annotations

import logging
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.telemetry import read_telemetry
from server.db.models import Throw
from server.jobs.specs import DiagnosisSpec, job_dir

log = logging.getLogger(__name__)


def landed_with_telemetry(machine_id: str) -> tuple:
    """SQL conditions of the throws a diagnosis can use: the machine's landed throws with telemetry."""
    return (Throw.machine_id == machine_id, Throw.status == "landed", Throw.telemetry_path.is_not(None))


def export(sessions: sessionmaker[Session], data_dir: Path, machine_id: str, limit: int, directory: Path) -> int:
    """Write the machine's newest ``limit`` landed throws with telemetry as a dataset.

    The impact time is the telemetry's "landed" event (the executor stamps it at the impact
    report, within one 10 ms tick). A missing or corrupt telemetry file drops that throw (logged),
    not the export. Returns the number of throws written.
    """
    from sim_twin.diagnosis.dataset import write

    with sessions() as db:
        rows = list(db.scalars(select(Throw).where(*landed_with_telemetry(machine_id))
                               .order_by(Throw.requested_at.desc()).limit(limit)))
    out = []
    for t in rows:
        if t.telemetry_path is None:  # landed_with_telemetry excludes these
            raise RuntimeError(f"throw {t.id} selected for export has no telemetry path")
        path = Path(data_dir) / t.telemetry_path
        try:
            data = path.read_bytes()
            tel = read_telemetry(data)
        except Exception as e:  # noqa: BLE001  a missing or corrupt file drops that throw, not the run
            log.warning("throw %s: telemetry %s unusable (%s), skipped", t.id, path, e)
            continue
        landed = [s for s, p in zip(tel["event_t_s"], tel["event_phase"]) if p == "landed"]
        out.append(({"throw_id": t.id, "mode": t.mode, "target_m": t.target_m, "impact_m": t.impact_m,
                     "impact_stamp_s": float(landed[0]) if landed else None, "status": t.status,
                     "policy_version": t.policy_version}, data))
    write(directory, out, machine_id=machine_id, source={"exported_from": "slinger server", "limit": limit})
    return len(out)


def run(sessions: sessionmaker[Session], data_dir: Path, job_id: str, spec: DiagnosisSpec, progress) -> dict:
    """Export and diagnose; returns the job's result ``{"throws", "verdict"}``.

    Raises:
        server.jobs.JobCancelled: from ``progress``.
        Exception: whatever the export or the diagnosis raised (the job fails with it).
    """
    from sim_twin.diagnosis.diagnose import diagnose

    folder = job_dir(data_dir, job_id)
    if spec.upload:
        from server.analysis.diagnosis_upload import upload_dir, uploaded
        from sim_twin.diagnosis import rosbag

        progress(0.0, "converting the uploaded rosbag2 bags")
        bags, mapping, impacts = uploaded(upload_dir(data_dir, spec.upload))
        rosbag.convert(bags, mapping, impacts, folder / "dataset")
        n = len(bags)
    else:
        progress(0.0, "exporting throws")
        n = export(sessions, data_dir, spec.machine_id, spec.limit, folder / "dataset")
    progress(0.1, f"diagnosing {n} throws")
    report = diagnose(folder / "dataset", folder / "report", workers=spec.workers)
    return {"throws": n, "verdict": report["verdict"]}
