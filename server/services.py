"""The server's services, built once from the settings in dependency order (:func:`build_services`).

Each service is constructed from the ones before it (storage and sessions, the result store, the
Zenoh session and the fleet link, then its consumers: live push, throws, the 3D scene, the
reconciler, jobs, policies, previews, diagnosis and adaptation runs, alarms, the drift watch) and
wired with plain references; nothing is patched in after construction. :meth:`Services.start`
starts them in that order, :meth:`Services.stop` stops them in the reverse one.
:func:`server.app.create_app`'s lifespan does both and publishes each service on the application
under its field name (``app.state.fleet`` ...), where :mod:`server.api.deps` hands them to the routes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import zenoh
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from runtime.heap import HeapTrimmer, bound_heap
from server.accounts import session_file
from server.accounts.auth import AuditBacklog, SessionMirror, user_for_token
from server.accounts.login_guard import LoginGuard
from server.analysis.adaptation import AdaptationRuns
from server.analysis.diagnosis import DiagnosisRuns
from server.analysis.drift import DriftWatch
from server.config import Settings
from server.console.alarms import AlarmService
from server.console.live import LiveHub
from server.console.scene import ConsoleScene
from server.db.migrate import upgrade
from server.db.models import Throw
from server.db.session import make_engine, make_sessionmaker
from server.fleet.command_signer import CommandSigner
from server.fleet.events import on_results
from server.fleet.link import Fleet
from server.fleet.reconcile import Reconciler
from server.fleet.results import ResultStore
from server.jobs import JobQueue, JobStore, queue_url
from server.jobs import tasks as job_tasks
from server.jobs.watch import JobWatcher
from server.policies.versions import PolicyService
from server.site.storage import StorageMonitor, classify
from server.throws.gate import GateLimits
from server.throws.previews import PreviewService
from server.throws.service import ThrowService
from server.throws.targets import serve_refusal

log = logging.getLogger(__name__)

ESTOP_LATCH_FILE = "estop_latches.json"
"""The server's E-STOP latches (server.fleet.estop), in the data directory."""
SESSION_MIRROR_FILE = session_file.FILE_NAME
"""The session mirror's file (server.accounts.session_file), in the data directory beside the latches."""


@dataclass
class Services:
    """Every service of one server process; a field's name is its name on ``app.state``."""

    settings: Settings
    storage: StorageMonitor
    engine: Engine
    sessions: sessionmaker[Session]
    audit_backlog: AuditBacklog
    session_mirror: SessionMirror
    store: ResultStore
    zenoh_session: zenoh.Session
    own_zenoh_session: bool
    fleet: Fleet
    live: LiveHub
    login_guard: LoginGuard
    throws: ThrowService
    scene: ConsoleScene | None
    reconciler: Reconciler
    jobs: JobQueue
    policies: PolicyService
    previews: PreviewService
    job_watcher: JobWatcher
    diagnosis_runs: DiagnosisRuns
    adaptation_runs: AdaptationRuns
    alarms: AlarmService
    drift: DriftWatch

    def publish(self, state: object) -> None:
        """Set every service as an attribute of ``state`` (the application's ``app.state``)."""
        for f in fields(self):
            setattr(state, f.name, getattr(self, f.name))

    def start(self) -> None:
        """Start the services that run threads or servers. The live hub is a fleet consumer before
        the fleet's subscribers exist, so it hears every event."""
        self.live.start()
        self.fleet.start()
        self.reconciler.start()
        self.job_watcher.start()
        self.policies.start()
        if self.scene is not None:
            self.scene.start()
            self.fleet.add_consumer(on_results(ResultDrawer(self.scene, self.sessions, self.store)))

    def stop(self) -> None:
        """Stop everything :meth:`start` started, in the reverse order; then close the Zenoh
        session (when it is the server's own), the log-in guard (its pending audit entries are
        written first), the session mirror, the audit backlog and the database engine (disposed,
        unless its files are unwritable: server.site.storage). Safe after a partial start."""
        if self.scene is not None:
            self.scene.stop()
        self.policies.stop()
        self.job_watcher.stop()
        self.reconciler.stop()
        self.live.stop()
        self.fleet.stop()
        if self.own_zenoh_session:
            self.zenoh_session.close()
        self.login_guard.close()
        self.session_mirror.stop()
        self.audit_backlog.flush()
        self.storage.release(self.engine)


def build_services(settings: Settings, zenoh_session: zenoh.Session | None = None) -> Services:
    """Build every service from ``settings``, in dependency order (nothing is started yet).

    Args:
        settings: the server's settings.
        zenoh_session: an already open session to use (the caller keeps ownership and closes it);
            default: one is opened from the settings, and :meth:`Services.stop` closes it.

    Runs ``alembic upgrade head`` first when ``settings.auto_migrate`` (skipped, with the reason
    logged, while the storage has a fault).
    """
    bound_heap()  # before the server's threads start: fewer arenas, large blocks mapped (runtime.heap)
    storage = StorageMonitor(settings.database_url, settings.storage_min_free_bytes)
    if settings.auto_migrate:
        _migrate(settings.database_url, storage)
    engine = make_engine(settings.database_url, settings.database_busy_timeout_s)
    storage.guard(engine)
    sessions = make_sessionmaker(engine, before_use=storage.before_use)
    # the E-STOP and the machine list authorise from memory and audit later (docs/safety.md)
    audit_backlog = AuditBacklog(sessions)
    heap_trimmer = HeapTrimmer()  # glibc's free heap back to the system every minute (runtime.heap)

    def tick() -> None:
        heap_trimmer.tick()
        audit_backlog.flush()

    session_mirror = SessionMirror(sessions, on_tick=tick,
                                   file=session_file.SessionFile(settings.data_dir / SESSION_MIRROR_FILE))
    session_mirror.watch(sessions)
    session_mirror.start()
    store = ResultStore(sessions, settings.data_dir)
    own_session = zenoh_session is None
    zsession = zenoh_session if zenoh_session is not None else open_zenoh(settings)
    fleet = Fleet(zsession, store, settings.query_timeout_s, signer=CommandSigner(settings.resolved_site_dir),
                  estop_latch_file=settings.data_dir / ESTOP_LATCH_FILE)
    live_hub = LiveHub(fleet)
    login_guard = LoginGuard(settings.login_failures_per_user, settings.login_failures_per_address,
                             settings.login_workers, settings.login_max_pending,
                             per_user_address=settings.login_failures_per_user_address)
    throws = ThrowService(fleet, sessions, settings.keep_out_zones,
                          gate=GateLimits.from_settings(settings), machine_status=live_hub.status)
    scene = _make_scene(fleet, throws, live_hub, settings, sessions) if settings.viser_enabled else None
    alarms = AlarmService(sessions, publish=live_hub.publish, simulated=lambda mid: _simulated(fleet, mid))

    def throw_lost(throw_id: str) -> None:  # closed by the reconciler: no ThrowResult comes, so no ResultStored
        live_hub.throw_closed(throw_id)
        alarms.on_lost(throw_id)

    reconciler = Reconciler(fleet, sessions, store.mark_lost, settings.result_grace_s, settings.runtime_gone_s,
                            settings.reconcile_period_s, handshake_s=settings.query_timeout_s + 2.0, on_lost=throw_lost)
    fleet.add_consumer(reconciler.on_event)  # passes follow the fleet's events
    jobs = JobQueue(queue_url(settings), JobStore(sessions), job_tasks.execute)
    if jobs.url == "immediate":  # tests: jobs run in this process
        job_tasks.bind(job_tasks.WorkerContext(sessions, settings.data_dir, settings, jobs))
    policies = PolicyService(fleet, sessions, store, settings, jobs, on_deployment=live_hub.deployment_changed)
    previews = PreviewService(fleet, sessions, throws, jobs, settings.data_dir, settings.clearance_radius_m,
                              settings.preview_profile, settings.release_check_radius_m)
    throws.previews = previews.get  # a throw looks its preview up (built after the throws)
    job_watcher = JobWatcher(jobs.store, live_hub.publish)
    diagnosis_runs = DiagnosisRuns(sessions, jobs, settings.data_dir)
    adaptation_runs = AdaptationRuns(diagnosis_runs, policies, previews, jobs)

    def publish_drift(event: str, data: dict) -> None:  # a drift alert is also an alarm
        live_hub.publish(event, data)
        alarms.on_drift(data)

    drift = live_hub.drift = DriftWatch(sessions, settings.data_dir, diagnosis_runs,
                                        webhook_url=settings.drift_webhook_url, publish=publish_drift)
    alarms.drift_ack = drift.acknowledge
    fleet.add_consumer(on_results(drift.on_result))
    fleet.add_consumer(alarms.on_event)
    return Services(settings=settings, storage=storage, engine=engine, sessions=sessions, audit_backlog=audit_backlog,
                    session_mirror=session_mirror, store=store, zenoh_session=zsession, own_zenoh_session=own_session,
                    fleet=fleet, live=live_hub, login_guard=login_guard, throws=throws, scene=scene,
                    reconciler=reconciler, jobs=jobs, policies=policies, previews=previews, job_watcher=job_watcher,
                    diagnosis_runs=diagnosis_runs, adaptation_runs=adaptation_runs, alarms=alarms, drift=drift)


def open_zenoh(settings: Settings) -> zenoh.Session:
    """Open the server's Zenoh session from settings (runtime.zenoh_session builds the config)."""
    from runtime.zenoh_acl import machines_in_site, site_acl
    from runtime.zenoh_session import TlsFiles, open_session

    tls_dir = settings.zenoh_tls_dir
    return open_session(
        mode=settings.zenoh_mode,
        listen=tuple(settings.zenoh_listen),
        connect=tuple(settings.zenoh_connect),
        multicast_scouting=settings.zenoh_multicast_scouting,
        tls=TlsFiles.from_site(tls_dir, "server") if tls_dir else None,
        access_control=site_acl(machines_in_site(tls_dir)) if tls_dir else None,
    )


def _make_scene(fleet: Fleet, throws: ThrowService, live_hub: LiveHub, settings: Settings,
                sessions: sessionmaker[Session]) -> ConsoleScene:
    """The 3D view, judging clicked targets like a throw request would (mode geometry, the
    policy's trained range, keep-out zones), pushing console changes live, and binding a view to a
    console only for the console's owner (the session cookie of its websocket)."""

    def refusal(machine_id: str, mode: str, target) -> str | None:
        state = fleet.latest_state(machine_id)
        if state is None:
            return f"no state from machine {machine_id}"
        return serve_refusal(mode, target, state.q[0], throws.target_range(machine_id, mode), settings.keep_out_zones)

    def console_changed(con: dict) -> None:
        live_hub.publish("console", con, console_id=con["console_id"])

    def authorise(token: str | None) -> str | None:
        with sessions() as db:
            user = user_for_token(db, token)
            return user.username if user is not None else None

    return ConsoleScene(fleet, settings.viser_host, settings.viser_port, refusal=refusal, band=throws.target_range,
                        zones=settings.keep_out_zones, on_console_change=console_changed, authorise=authorise,
                        public_host=settings.viser_public_host)


class ResultDrawer:
    """The 3D scene's consumer of stored results: draws each stored throw in the views showing
    its machine (called with the throw id, :func:`server.fleet.events.on_results`)."""

    def __init__(self, scene: ConsoleScene, sessions, store: ResultStore):
        self.scene, self.sessions, self.store = scene, sessions, store

    def __call__(self, throw_id: str) -> None:
        with self.sessions() as db:
            row = db.get(Throw, throw_id)
            if row is None:
                return
            self.scene.show_throw(row.machine_id, self.store.telemetry_file(row), row.impact_m, row.target_m)


def _simulated(fleet: Fleet, machine_id: str) -> bool:
    """Whether the fleet knows ``machine_id`` as a simulated machine (RuntimeInfo or MachineState)."""
    info, state = fleet.last_info(machine_id), fleet.latest_state(machine_id)
    return bool((info is not None and info.simulated) or (state is not None and state.simulated))


def _migrate(database_url: str, storage: StorageMonitor) -> None:
    """``alembic upgrade head`` unless the storage has a fault (then the server starts in the
    fault state, /api/health names it, and the migration runs at the next start)."""
    fault = storage.check_files()
    if fault is not None:
        log.error("database not migrated: %s", fault.reason)
        return
    try:
        upgrade(database_url)
    except Exception as e:
        fault = classify(e)
        if fault is None:
            raise
        storage.report(fault)
        log.error("database not migrated: %s", fault.reason)
