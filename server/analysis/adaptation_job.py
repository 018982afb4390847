"""The ``adaptation`` job's body (worker side): adapt a policy version to a diagnosed site's
fitted profile (sim_twin.adaptation.adapt.adapt, aim correction in the CPU twin) and register the result as
a new policy version, whose twin evaluation is another job.

Files (the adapted ONNX, its adaptation.json) go under the job's folder; status, progress and
the new version's id live in the job's row only.
"""

from __future__ import annotations

from pathlib import Path

from server.jobs.specs import job_dir


def run(policies, data_dir: Path, job, progress) -> dict:
    """Adapt and register; returns ``{"policy_version_id", "policy_version", "lines"}``.

    Args:
        policies: server.policies.versions.PolicyService (registers the version).
        data_dir: the data folder (base policy files are relative to it).
        job: server.jobs.tasks.JobRun with an AdaptationSpec.
        progress: ``progress(fraction, message)``; each adaptation log line is one message.

    Raises:
        server.jobs.JobCancelled: from ``progress``.
    """
    from sim_twin.adaptation.adapt import adapt

    spec, lines = job.spec, []

    def line(text: str) -> None:
        lines.append(text)
        progress(min(0.95, 0.05 * len(lines)), text)

    name = f"{spec.base_version}-{spec.machine_id}-{job.id[-6:]}"
    res = adapt(spec.profile, Path(data_dir) / spec.base_path, job_dir(data_dir, job.id), name=name, method="aim",
                diagnosis_report=spec.report, throws=spec.throws, rounds=spec.rounds, workers=spec.workers,
                progress=line)
    row = policies.add_version(res["manifest"], Path(res["policy"]), job.requested_by,
                               notes=f"adapted to diagnosis {spec.diagnosis_id} of {spec.machine_id}",
                               action="policy_adapt")
    return {"policy_version_id": row.id, "policy_version": row.name, "lines": lines}
