"""What each job kind does, run by :func:`execute` in a worker process.

Every runner is ``runner(ctx, params, progress) -> dict`` (the JSON result): ``ctx`` is the
:class:`WorkerContext`, ``params`` the job row's parameters, ``progress(fraction, message)``
records progress and raises :class:`~server.jobs.store.JobCancelled` when the job was
cancelled. MuJoCo and sim_twin are imported inside the runners only: this module is imported by
the API process too (to register the queue's task).

Kinds and parameters:

* ``preview``: ``onnx_path`` (relative to the data dir), ``sha256``, ``request`` (the keyword
  arguments of sim_twin.preview.PreviewRequest), ``profile_path`` (the site profile or None)
  -> sim_twin.preview.preview_throw's summary.
* ``catalog``: none -> ``{"effects": {name: description}}`` (sim_twin.effects).
* ``evaluation``: ``version_id``, ``distances_m``, ``throws`` -> the evaluation report; also
  written to the policy version's row (``evaluation_status``, ``metrics``).
* ``diagnosis``: ``run_id``, ``machine_id``, ``limit``, ``workers`` -> the run's status
  (server.diagnosis: files under ``<data_dir>/diagnosis/<run_id>``).
* ``adaptation``: ``run_id`` and the inputs server.adaptation.AdaptationRuns.start checked ->
  the run's status; the adapted policy becomes a version (its evaluation is another job).
* ``probe``: ``steps``, ``step_s``, optional ``fail`` (a message to fail with): a worker
  health check that reports progress and can be cancelled between steps. Fault injection for
  tests (not accepted by the API): ``kill_worker_at_step`` makes the worker process SIGKILL
  itself at that step (a worker dying mid-job, server.jobs.leases).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from server.jobs.leases import LEASE_S, WorkerIdentity
from server.jobs.store import JobCancelled, JobStore

log = logging.getLogger(__name__)


class JobRefused(Exception):
    """A job that cannot be done as asked; ``status_code`` is the HTTP status the API answers."""

    def __init__(self, status_code: int, detail: str):
        super().__init__(detail)
        self.status_code, self.detail = status_code, detail


@dataclass
class WorkerContext:
    """What runners need: the database, the data dir (policy files, telemetry, reports), the
    settings (evaluation sample sizes) and the queue (jobs that start jobs)."""

    sessions: sessionmaker[Session]
    data_dir: Path
    settings: object = None
    jobs: object = None
    identity: WorkerIdentity = field(default_factory=WorkerIdentity)
    lease_s: float = LEASE_S
    """Lease of a started job (server.jobs.leases), renewed by the worker's heartbeat."""
    store: JobStore = field(init=False)
    runners: dict = field(default_factory=dict)
    """Loaded policy runners by SHA-256 (previews re-use them)."""
    profiles: dict = field(default_factory=dict)
    """Site profiles of previews by source."""
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self):
        self.store = JobStore(self.sessions)
        self.data_dir = Path(self.data_dir)

    @property
    def name(self) -> str:
        """``host:pid`` of this worker."""
        return self.identity.name


_CONTEXT: WorkerContext | None = None


def bind(ctx: WorkerContext) -> None:
    """Set the context :func:`execute` uses in this process (the worker at start-up)."""
    global _CONTEXT
    _CONTEXT = ctx


def execute(job_id: str) -> None:
    """Run job ``job_id`` (the Huey task of every lane): status, progress, result in its row."""
    ctx = _CONTEXT
    if ctx is None:
        raise RuntimeError("no worker context bound (server.jobs.tasks.bind)")
    me = ctx.identity.id
    job = ctx.store.start(job_id, ctx.identity, ctx.lease_s)
    if job is None:
        log.info("job %s skipped (unknown, cancelled, finished or already running)", job_id)
        return
    t0 = time.monotonic()
    log.info("job %s (%s) started, attempt %d", job_id, job["kind"], job["attempts"])
    try:
        result = RUNNERS[job["kind"]](ctx, job["params"] or {},
                                      lambda f, m=None: ctx.store.progress(job_id, f, m, worker_id=me))
        ctx.store.finish(job_id, "done", result=_json_safe(result), worker_id=me)
        log.info("job %s (%s) done in %.2f s", job_id, job["kind"], time.monotonic() - t0)
    except JobCancelled:
        if ctx.store.finish(job_id, "cancelled", worker_id=me):
            log.info("job %s (%s) cancelled", job_id, job["kind"])
        else:
            log.warning("job %s (%s) was taken from this worker (lease expired); stopped", job_id, job["kind"])
    except JobRefused as e:
        ctx.store.finish(job_id, "failed", result={"status_code": e.status_code}, error=e.detail, worker_id=me)
    except Exception as e:  # recorded in the row for the console
        log.exception("job %s (%s) failed", job_id, job["kind"])
        ctx.store.finish(job_id, "failed", error=f"{type(e).__name__}: {e}", worker_id=me)


def _json_safe(result) -> dict:
    """Round-trip through JSON (numpy scalars and tuples become plain JSON values)."""
    return json.loads(json.dumps(result, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


# --- runners ----------------------------------------------------------------------------------
def run_preview(ctx: WorkerContext, params: dict, progress) -> dict:
    from runtime.policy import PolicyError, PolicyRunner
    from sim_twin.preview import PreviewRequest, preview_throw

    sha = params["sha256"]
    with ctx.lock:
        runner = ctx.runners.get(sha)
    if runner is None:
        try:
            runner = PolicyRunner.load(ctx.data_dir / params["onnx_path"])
        except (PolicyError, OSError) as e:
            raise JobRefused(409, f"policy {sha[:12]}… does not load on the worker: {e}") from e
        with ctx.lock:
            ctx.runners[sha] = runner
    return preview_throw(runner, PreviewRequest(**params["request"]), _site_profile(ctx, runner, params.get("profile_path")))


def _site_profile(ctx: WorkerContext, runner, profile_path: str | None):
    """The profile a preview runs under: the policy's own site profile (adapted versions), else
    the server's (Settings.preview_profile), else nominal; cached per source."""
    from sim_twin.preview import site_profile

    key = ("policy", runner.sha256) if runner.manifest.get("site_profile") else ("file", profile_path)
    with ctx.lock:
        if key not in ctx.profiles:
            ctx.profiles[key] = site_profile(runner.manifest) if key[0] == "policy" else site_profile(None, profile_path)
        return ctx.profiles[key]


def run_catalog(ctx: WorkerContext, params: dict, progress) -> dict:
    from sim_twin.effects import EFFECTS

    return {"effects": {name: cls.describe() for name, cls in EFFECTS.items()}}


def run_evaluation(ctx: WorkerContext, params: dict, progress) -> dict:
    from server.policies import evaluate_version

    return evaluate_version(ctx.sessions, ctx.data_dir, params["version_id"], params["distances_m"],
                            params["throws"], progress)


def run_diagnosis(ctx: WorkerContext, params: dict, progress) -> dict:
    from server.diagnosis import DiagnosisRuns

    return DiagnosisRuns(ctx.sessions, ctx.data_dir).run(params["run_id"], params["machine_id"], params["limit"],
                                                         params.get("workers"), progress)


def run_adaptation(ctx: WorkerContext, params: dict, progress) -> dict:
    from server.adaptation import AdaptationRuns
    from server.policies import PolicyService
    from server.results import ResultStore

    policies = PolicyService(None, ctx.sessions, ResultStore(ctx.sessions, ctx.data_dir), ctx.settings, ctx.jobs)
    return AdaptationRuns(None, policies, None, ctx.data_dir).run(params, progress)


def run_probe(ctx: WorkerContext, params: dict, progress) -> dict:
    steps, step_s = int(params.get("steps", 1)), float(params.get("step_s", 0.0))
    kill_at = params.get("kill_worker_at_step")
    for i in range(steps):
        progress(i / max(steps, 1), f"step {i + 1} of {steps}")
        if kill_at is not None and i == int(kill_at):
            log.warning("probe: killing this worker process (kill_worker_at_step=%s)", kill_at)
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(step_s)
    if params.get("fail"):
        raise RuntimeError(str(params["fail"]))
    progress(1.0, "done")
    return {"worker": ctx.name, "steps": steps}


RUNNERS = {"preview": run_preview, "catalog": run_catalog, "evaluation": run_evaluation,
           "diagnosis": run_diagnosis, "adaptation": run_adaptation, "probe": run_probe}
