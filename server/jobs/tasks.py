"""What each job kind does, run by :func:`execute` in a worker process.

Every runner is ``runner(ctx, job, progress) -> dict`` (the JSON result): ``ctx`` is the
:class:`WorkerContext`, ``job`` the :class:`JobRun` (id and typed spec), ``progress(fraction, message)``
records progress and raises :class:`~server.jobs.store.JobCancelled` when the job was
cancelled. MuJoCo and sim_twin are imported inside the runners only: this module is imported by
the API process too (to register the queue's task).

Kinds and their typed parameters (server.jobs.specs, checked at submit and again here):

* ``preview`` (PreviewSpec) -> sim_twin.preview.preview.preview_throw's summary.
* ``catalog`` (CatalogSpec) -> ``{"effects": {name: description}}`` (sim_twin.twin.effects).
* ``evaluation`` (EvaluationSpec) -> the evaluation report; also written to the policy
  version's row (``evaluation_status``, ``metrics``).
* ``diagnosis`` (DiagnosisSpec) -> ``{"throws", "verdict"}``; the dataset and report files under
  the job's folder (server.analysis.diagnosis_job).
* ``adaptation`` (AdaptationSpec) -> the new policy version (server.analysis.adaptation_job).
* ``probe`` (ProbeSpec): a worker health check that reports progress and can be cancelled
  between steps. Fault injection for tests (not accepted by the API): ``kill_worker_at_step``
  makes the worker process SIGKILL itself at that step (a worker dying mid-job, server.jobs.leases).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

from sqlalchemy.orm import Session, sessionmaker

from server.config import Settings
from server.errors import Conflict, kind_of
from server.jobs.leases import LEASE_S, WorkerIdentity
from server.jobs.specs import (
    AdaptationSpec,
    CatalogSpec,
    DiagnosisSpec,
    EvaluationSpec,
    JobSpecError,
    PreviewSpec,
    ProbeSpec,
    parse_spec,
)
from server.jobs.store import JobCancelled, JobStore

log = logging.getLogger(__name__)


def _set(event: threading.Event) -> threading.Event:
    event.set()
    return event


WARM_WAIT_S = 60.0
"""Longest wait of a preview for its worker's warm-up (WorkerContext.warm_previews), s."""


WARMING_UP_MESSAGE = "the twin is warming up on the job worker (its first previews after a start take a few seconds more)"
"""Progress message of a preview that waits for its worker's warm-up."""


class JobRefused(Conflict):
    """A job that this worker cannot do as asked (e.g. its policy file does not load here); its
    kind (server.errors.kind_of: ``"conflict"``) is kept in the job's result as ``refused``, and
    the API raises that kind for it (server.throws.previews)."""


@dataclass
class WorkerContext:
    """What runners need: the database, the data dir (policy files, telemetry, reports), the
    settings (evaluation sample sizes) and the queue (jobs that start jobs)."""

    sessions: sessionmaker[Session]
    data_dir: Path
    settings: Settings | None = None
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
    preview_pool: Executor | None = None
    """Processes for the previews' Monte Carlo rollouts (:meth:`start_preview_pool`), or None."""
    warmed: threading.Event = field(default_factory=lambda: _set(threading.Event()))
    """Set once :meth:`warm_previews` has made the nominal previews warm; a preview waits for it
    (at most WARM_WAIT_S): running beside that part only slowed both (one interpreter lock, the
    same policy loaded twice). Set at once where nothing warms up (tests, a heavy-only worker)."""
    nominals: Any = None
    """The previews' nominal rollouts by request (sim_twin.preview.preview.NominalCache, made by
    the first preview): the console's ellipse reuses the nominal it previewed just before."""

    def __post_init__(self):
        self.store = JobStore(self.sessions)
        self.data_dir = Path(self.data_dir)

    def start_preview_pool(self) -> None:
        """Start ``settings.preview_processes`` processes for the previews' Monte Carlo and import
        the twin in them (sim_twin.preview.preview.warm_up); none for fewer than 2."""
        from sim_twin.preview.preview import warm_up
        from sim_twin.twin.pools import process_pool

        n = self.settings.preview_processes if self.settings is not None else 0
        if n >= 2 and self.preview_pool is None:
            self.preview_pool = process_pool(n)
            warm_up(self.preview_pool, n)

    def policy_runner(self, sha: str, onnx_path: str):
        """(the loaded policy runner of SHA-256 ``sha``, True if this call loaded it): from
        :attr:`runners`, else loaded from ``onnx_path`` (relative to the data dir) and kept there.

        Raises:
            runtime.policy.PolicyError, OSError: the file does not load.
        """
        from runtime.policy import PolicyRunner

        with self.lock:
            runner = self.runners.get(sha)
        if runner is not None:
            return runner, False
        loaded = PolicyRunner.load(self.data_dir / onnx_path)
        with self.lock:
            runner = self.runners.setdefault(sha, loaded)  # another thread may have loaded it meanwhile
        return runner, runner is loaded

    def warm_previews(self) -> None:
        """Make this worker's first preview as fast as its next ones (a background thread of
        ``slinger worker``; :attr:`warmed` is set once the nominal previews are warm, and
        previews wait for it): load the
        newest policy version of each mode that has a file (the deployed ones in the usual case:
        ``slinger up`` records them before it starts the worker) here and in the preview pool,
        run one nominal preview of each from the ready pose (MuJoCo's model, the release check,
        the first inference, numpy's lazy imports), import scipy.stats (the Monte Carlo's Sobol
        points, sim_twin.preview.preview.warm_imports) and run one small Monte Carlo in the pool.
        Without it the first preview of a fresh worker took 1.6 s and its ellipse 6.8 s at a 1-min
        load of 1-4 on the 2-core development VM (tests/benchmarks/bench_console_aim.py
        --breakdown, first sample). Errors are logged, never raised: a policy that does not load
        is refused by its preview as before."""
        from sqlalchemy import select

        from runtime.recovery import READY_POSE
        from server.db.models import PolicyVersion
        from sim_twin.preview.preview import PreviewRequest, preview_throw, warm_imports, warm_policy

        t_start = time.monotonic()
        try:
            with self.sessions() as db:
                rows = db.execute(select(PolicyVersion.mode, PolicyVersion.sha256, PolicyVersion.onnx_path)
                                  .where(PolicyVersion.onnx_path.is_not(None))
                                  .order_by(PolicyVersion.created_at.desc())).all()
            newest: dict[str, tuple[str, str]] = {}
            for mode, sha, path in rows:
                if path is not None:  # the query's filter, for the type checker
                    newest.setdefault(mode, (sha, path))
            radius = self.settings.release_check_radius_m if self.settings is not None else None
            processes = self.settings.preview_processes if self.settings is not None else 2
            profile_path = str(self.settings.preview_profile) if self.settings and self.settings.preview_profile else None
            q0 = [0.0, *READY_POSE, 0.0, 0.0]
            loading, requests = [], []
            for mode, (sha, path) in sorted(newest.items()):
                t0 = time.monotonic()
                try:
                    runner, _ = self.policy_runner(sha, path)
                    if self.preview_pool is not None:
                        loading += warm_policy(self.preview_pool, processes, runner.path, radius is not None)
                    lo, hi = runner.manifest.get("target_range_m", (6.0, 10.0))
                    req = PreviewRequest(mode, [0.5 * (float(lo) + float(hi)), 0.0, 0.0], q0, [0.0] * 6, rollouts=1,
                                         release_check_radius_m=radius)
                    profile = _site_profile(self, runner, profile_path)
                    preview_throw(runner, req, profile)
                    requests.append((runner, req, profile))
                    log.info("preview warm-up: %s policy %s… ready in %.2f s", mode, sha[:12], time.monotonic() - t0)
                except Exception:
                    log.exception("preview warm-up of the %s policy %s… failed", mode, sha[:12])
            log.info("preview warm-up: nominal previews ready in %.2f s", time.monotonic() - t_start)
            self.warmed.set()  # what the Monte Carlo needs besides goes on beside the previews
            warm_imports()
            for f in loading:
                f.result()
            if requests and self.preview_pool is not None:  # the pool processes' first rollouts
                runner, req, profile = requests[0]
                preview_throw(runner, dataclasses.replace(req, rollouts=12 * processes, param_rollouts=processes),
                              profile, pool=self.preview_pool)
            log.info("preview warm-up done in %.2f s", time.monotonic() - t_start)
        except Exception:
            log.exception("preview warm-up failed")
        finally:
            self.warmed.set()

    def close(self) -> None:
        """Stop the preview pool's processes."""
        if self.preview_pool is not None:
            self.preview_pool.shutdown(cancel_futures=True)
            self.preview_pool = None

    @property
    def name(self) -> str:
        """``host:pid`` of this worker."""
        return self.identity.name


SpecT = TypeVar("SpecT")


@dataclass(frozen=True)
class JobRun(Generic[SpecT]):
    """What a runner is given about its job: ``id`` (its files go under
    ``server.jobs.specs.job_dir(data_dir, id)``), the parsed ``spec`` (the spec class of its kind,
    server.jobs.specs.parse_spec) and ``requested_by``."""

    id: str
    spec: SpecT
    requested_by: str | None = None


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
        spec = parse_spec(job["kind"], job["params"])
    except JobSpecError as e:
        ctx.store.finish(job_id, "failed", error=str(e), worker_id=me)
        return
    try:
        result = RUNNERS[job["kind"]](ctx, JobRun(job_id, spec, job["requested_by"]),
                                      lambda f, m=None: ctx.store.progress(job_id, f, m, worker_id=me))
        ctx.store.finish(job_id, "done", result=_json_safe(result), worker_id=me)
        log.info("job %s (%s) done in %.2f s", job_id, job["kind"], time.monotonic() - t0)
    except JobCancelled:
        if ctx.store.finish(job_id, "cancelled", worker_id=me):
            log.info("job %s (%s) cancelled", job_id, job["kind"])
        else:
            log.warning("job %s (%s) was taken from this worker (lease expired); stopped", job_id, job["kind"])
    except JobRefused as e:
        ctx.store.finish(job_id, "failed", result={"refused": kind_of(e)}, error=e.detail, worker_id=me)
    except Exception as e:  # recorded in the row for the console
        log.exception("job %s (%s) failed", job_id, job["kind"])
        ctx.store.finish(job_id, "failed", error=f"{type(e).__name__}: {e}", worker_id=me)


def _json_safe(result) -> dict:
    """Round-trip through JSON (numpy scalars and tuples become plain JSON values)."""
    return json.loads(json.dumps(result, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


# --- runners ----------------------------------------------------------------------------------
def run_preview(ctx: WorkerContext, job: JobRun[PreviewSpec], progress) -> dict:
    from runtime.policy import PolicyError
    from sim_twin.preview.preview import NominalCache, PreviewRequest, preview_throw, warm_policy

    spec = job.spec
    sha = spec.sha256
    try:
        runner, loaded_now = ctx.policy_runner(sha, spec.onnx_path)
    except (PolicyError, OSError) as e:
        raise JobRefused(f"policy {sha[:12]}… does not load on the worker: {e}") from e
    if loaded_now and ctx.preview_pool is not None and spec.request.get("rollouts", 0) <= 1:
        # a policy new to this worker, met in a nominal-only preview (the console's first
        # request): its Monte Carlo processes load it meanwhile, not in the ellipse's rollouts
        warm_policy(ctx.preview_pool, ctx.settings.preview_processes if ctx.settings else 2, runner.path,
                    spec.request.get("release_check_radius_m") is not None)
    if not ctx.warmed.is_set():  # said on the console's status line (web/js/console.js, job events)
        progress(0.0, WARMING_UP_MESSAGE)
    ctx.warmed.wait(WARM_WAIT_S)
    with ctx.lock:
        if ctx.nominals is None:
            ctx.nominals = NominalCache()
    return preview_throw(runner, PreviewRequest(**spec.request), _site_profile(ctx, runner, spec.profile_path),
                         pool=ctx.preview_pool, nominals=ctx.nominals)


def _site_profile(ctx: WorkerContext, runner, profile_path: str | None):
    """The profile a preview runs under: the policy's own site profile (adapted versions), else
    the server's (Settings.preview_profile), else nominal; cached per source."""
    from sim_twin.preview.preview import site_profile

    key = ("policy", runner.sha256) if runner.manifest.get("site_profile") else ("file", profile_path)
    with ctx.lock:
        if key not in ctx.profiles:
            ctx.profiles[key] = site_profile(runner.manifest) if key[0] == "policy" else site_profile(None, profile_path)
        return ctx.profiles[key]


def run_catalog(ctx: WorkerContext, job: JobRun[CatalogSpec], progress) -> dict:
    from sim_twin.twin.effects import EFFECTS

    return {"effects": {name: cls.describe() for name, cls in EFFECTS.items()}}


def run_evaluation(ctx: WorkerContext, job: JobRun[EvaluationSpec], progress) -> dict:
    from server.policies.validation import ValidationLimits
    from server.policies.versions import evaluate_version

    limits = ValidationLimits.from_settings(ctx.settings) if ctx.settings is not None else None
    return evaluate_version(ctx.sessions, ctx.data_dir, job.spec.version_id, job.spec.distances_m,
                            job.spec.throws, progress, limits)


def run_diagnosis(ctx: WorkerContext, job: JobRun[DiagnosisSpec], progress) -> dict:
    from server.analysis.diagnosis_job import run

    return run(ctx.sessions, ctx.data_dir, job.id, job.spec, progress)


def run_adaptation(ctx: WorkerContext, job: JobRun[AdaptationSpec], progress) -> dict:
    from server.analysis.adaptation_job import run
    from server.fleet.results import ResultStore
    from server.policies.versions import PolicyService

    policies = PolicyService(None, ctx.sessions, ResultStore(ctx.sessions, ctx.data_dir), ctx.settings, ctx.jobs)
    return run(policies, ctx.data_dir, job, progress)


def run_probe(ctx: WorkerContext, job: JobRun[ProbeSpec], progress) -> dict:
    spec = job.spec
    steps, step_s, kill_at = spec.steps, spec.step_s, spec.kill_worker_at_step
    for i in range(steps):
        progress(i / max(steps, 1), f"step {i + 1} of {steps}")
        if kill_at is not None and i == kill_at:
            log.warning("probe: killing this worker process (kill_worker_at_step=%s)", kill_at)
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(step_s)
    if spec.fail:
        raise RuntimeError(spec.fail)
    progress(1.0, "done")
    return {"worker": ctx.name, "steps": steps}


RUNNERS: dict[str, Callable[[WorkerContext, Any, Any], dict]] = {"preview": run_preview, "catalog": run_catalog, "evaluation": run_evaluation,
           "diagnosis": run_diagnosis, "adaptation": run_adaptation, "probe": run_probe}
