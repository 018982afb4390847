"""Typed parameters of every job kind (the ``params`` column of a ``jobs`` row).

A job's spec is checked twice: when it is submitted (:meth:`server.jobs.store.JobStore.create`
refuses a bad one before a row exists) and when a worker runs it (:func:`server.jobs.tasks.execute`
parses the stored JSON again, so a row written by an older or foreign producer fails with the
reason instead of half-running). Runners receive the parsed model, never a bare dict.

The ``jobs`` row is the only state of a job: status, progress, message, error and result live
there; the files a job makes live under :func:`job_dir` (``<data_dir>/jobs/<job_id>/``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.errors import Refused


class JobSpecError(Refused, ValueError):
    """A job's parameters do not match its kind's spec (the message names the fields)."""


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PreviewSpec(_Spec):
    """A twin preview of one throw (sim_twin.preview.preview.preview_throw)."""

    onnx_path: str = Field(description="policy file, relative to the data dir")
    sha256: str = Field(min_length=64, max_length=64)
    request: dict = Field(description="keyword arguments of sim_twin.preview.preview.PreviewRequest")
    meta: dict = Field(default_factory=dict, description="what the API keeps with the preview (machine, start pose)")
    profile_path: str | None = Field(None, description="site profile the preview runs under; None: nominal")


class CatalogSpec(_Spec):
    """The effects library's description (sim_twin.twin.effects); no parameters."""


class EvaluationSpec(_Spec):
    """A twin evaluation of a stored policy version (server.policies.versions.evaluate_version)."""

    version_id: int
    distances_m: list[float] = Field(min_length=1)
    throws: int = Field(ge=1)


class DiagnosisSpec(_Spec):
    """A sim-to-real gap diagnosis of a machine's newest landed throws, or of an uploaded set of
    rosbag2 bags (``upload``)."""

    machine_id: str = Field(min_length=1, max_length=64)
    limit: int = Field(50, ge=1, le=500, description="newest landed throws with telemetry to diagnose")
    workers: int | None = Field(None, ge=1, description="processes; None: every core of the worker")
    upload: str | None = Field(None, pattern=r"^[0-9a-f]{32}$",
                               description="an uploaded rosbag2 set, <data_dir>/uploads/<upload>/ (server.analysis.diagnosis_upload), "
                                           "converted instead of exporting stored throws")


class AdaptationSpec(_Spec):
    """An aim adaptation of a policy version to a finished diagnosis (sim_twin.adaptation.adapt.adapt)."""

    diagnosis_id: str
    machine_id: str
    mode: Literal["2d", "3d"]
    base_version: str
    base_path: str = Field(description="base policy file, relative to the data dir")
    profile: dict = Field(description="the diagnosis' fitted profile (profile_fitted.json)")
    report: dict | None = Field(None, description="the diagnosis report (its 1 sigma)")
    throws: int = Field(20, ge=2, le=200)
    rounds: int = Field(2, ge=1, le=4)
    workers: int | None = Field(None, ge=1)


class ProbeSpec(_Spec):
    """A worker health check; ``kill_worker_at_step`` is fault injection for tests (the API's
    POST /api/jobs does not accept it)."""

    steps: int = Field(1, ge=1, le=1000)
    step_s: float = Field(0.0, ge=0.0, le=10.0, allow_inf_nan=False)
    fail: str | None = Field(None, max_length=200)
    machine_id: str | None = Field(None, max_length=64)
    kill_worker_at_step: int | None = None


SPECS: dict[str, type[_Spec]] = {"preview": PreviewSpec, "catalog": CatalogSpec, "evaluation": EvaluationSpec,
                                 "diagnosis": DiagnosisSpec, "adaptation": AdaptationSpec, "probe": ProbeSpec}


def parse_spec(kind: str, params: dict | None) -> _Spec:
    """The typed spec of a ``kind`` job from its JSON parameters.

    Raises:
        JobSpecError: unknown kind, or parameters that do not match its spec (a sentence per field).
    """
    model = SPECS.get(kind)
    if model is None:
        raise JobSpecError(f"unknown job kind {kind!r}; one of {', '.join(SPECS)}")
    try:
        return model.model_validate(params or {})
    except ValidationError as e:
        why = "; ".join(f"{'.'.join(str(p) for p in err['loc']) or 'parameters'}: {err['msg']}" for err in e.errors())
        raise JobSpecError(f"bad parameters for a {kind} job: {why}") from None


def job_dir(data_dir: Path, job_id: str) -> Path:
    """The folder of a job's files, ``<data_dir>/jobs/<job_id>/`` (not created here)."""
    return Path(data_dir) / "jobs" / job_id
