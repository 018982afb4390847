"""Shared fixtures of the server tests: free ports, a migrated SQLite database, the app on a
Zenoh loopback endpoint, and a FAKE runtime that speaks the real protocol over real Zenoh.

Every Zenoh session here has multicast scouting off and explicit tcp/127.0.0.1 endpoints, and is
closed by its fixture (sessions with Python callbacks left open hang the interpreter at exit).
"""

from __future__ import annotations

import base64
import contextlib
import os
import socket
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sqlalchemy import create_engine, func, select, text
from sqlalchemy.exc import OperationalError

from runtime.protocol import keys
from runtime.command_auth import CommandVerifier, load_key, new_key, sign, write_key
from runtime.protocol.messages import (
    AbortAck,
    AbortRequest,
    EstopReset,
    EstopResetAck,
    LeaseAck,
    LeaseRequest,
    MachineState,
    PolicyInfo,
    ResultAck,
    ReturnToReady,
    ReturnToReadyAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    ThrowStatus,
    decode,
    encode,
)
from runtime.telemetry import TelemetryRecorder, write_mcap
from runtime.throw_geometry import impact_errors
from runtime.zenoh_session import open_session

# JAX's persistent compilation cache for every test and the processes they start: the tiny CPU
# trainings, their resumes and the MJX parity tests compile the same programs again and again (on
# a 2-core host a train-resume-export test took 173 s without it, 109 s from an empty cache, 45 s
# warm). Keyed by the program and the jaxlib version, so a changed environment compiles anew.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(tempfile.gettempdir()) / f"slinger-tests-jax-cache-{os.getuid()}"))


def pytest_configure(config) -> None:
    # Starlette's TestClient warns that it wants httpx2; not our concern here.
    config.addinivalue_line("filterwarnings", "ignore:Using `httpx` with `starlette.testclient`")
    config.addinivalue_line("filterwarnings", "ignore:No path_separator found")
    # Servers, workers and `slinger up` stacks started by tests run the test policies of tests/fixtures.py,
    # which are not throwers: the release check (runtime.release_check) would hold their releases. Their
    # settings (server.config.Settings.release_check_radius_m) switch it off for the previews and the
    # runtimes `slinger up` starts; runtimes a test starts itself get TEST_POLICY_CHECK. In-process
    # executors keep ExecutorConfig's default; tests that need it off say so.
    os.environ.setdefault("SLINGER_RELEASE_CHECK_RADIUS_M", "off")
    # MuJoCo's first import, with MUJOCO_GL unset or "glfw", imports pyGLFW, which reads each libglfw's
    # version in a `python -c` child. Imported here, before the watch, so that this one-off child is not
    # charged to whichever test happens to import MuJoCo first (a test run alone failed; in the tier a
    # module imported it at collection). A broken MuJoCo is left to the tests that use it.
    with contextlib.suppress(Exception):
        import mujoco  # noqa: F401
    _watch_process_starts()


TEST_POLICY_CHECK = ("--release-check-radius", "off")
"""Arguments of a `slinger runtime` that a test starts with the test policies (not throwers)."""

SYSTEM_MARKERS = ("browser", "postgres", "redis", "root", "torch", "processes", "slow", "acceptance")
"""Markers of tests outside the fast tier; each also gets ``system``, so that the fast tier is
``pytest -m "not system"`` (docs/development.md: test tiers)."""
FIXTURE_MARKERS = {"pg_url": "postgres", "browser": "browser", "module_browser": "browser", "netns": "root"}
"""Fixtures whose use marks a test: what the fixture needs (a service, Chromium, root)."""
SLOW_TESTS = {
    # processes: the test starts Python processes (Slinger's server, worker, runtime, plant or ROS 2
    # bridge; a policy validation child; a process pool of twin throws). Checked: a fast-tier test
    # that starts one fails (_fast_tier_starts_no_processes).
    "tests/test_stack.py": "processes", "tests/test_faults.py": "processes", "tests/test_supervise.py": "processes",
    "tests/test_claim_race.py": "processes", "tests/test_packaging.py": "processes",
    "tests/test_estop_faults.py": "processes", "tests/test_storage_faults.py": "processes",
    "tests/test_policy_validation.py": "processes", "tests/test_policies.py": "processes",
    "tests/test_policy_threads.py::test_sessions_start_the_threads_asked_for": "processes",
    "tests/test_release_sweep.py::test_a_policy": "processes", "tests/test_release_sweep.py::test_the_deployed": "processes",
    "tests/test_runtime_node.py::test_plant_and_runtime_throw_over_zenoh": "processes",
    "tests/test_ros2_bridge.py::test_slinger_up_ros2_throws_through_rclpy_nodes": "processes",
    "tests/test_ros2_bridge.py::test_bridge_node_on_fast_dds": "processes",
    "tests/test_ros2_bridge.py::test_bridge_refuses_a_wider_domain": "processes",
    "tests/test_job_leases.py::test_sqlite_job_of_a_killed_worker": "processes",
    "tests/test_job_state.py::test_a_diagnosis_killed_on_its_last_attempt": "processes",
    "tests/test_jobs.py::test_api_process_never_imports_mujoco": "processes",
    "tests/test_memory_bounds.py::test_the_heap_bounds": "processes",
    "tests/test_jobs.py::test_jobs_survive_an_api_restart": "processes",
    "tests/test_mjcf_chain.py::test_api_with_the_3d_view_on_never_imports_mujoco": "processes",
    "tests/test_adapt.py::test_console_flow_diagnosis_to_adapted_version": "processes",
    "tests/test_default_policy.py::test_diagnose_generate_outside_the_repo": "processes",
    "tests/test_matrix.py::test_tiny_matrix_writes_table_json_and_figure": "processes",
    "tests/test_site_coverage_diagnosis.py::test_a_split_profile_is_thrown_at_from_its_own_directory": "processes",
    "tests/test_matrix_gate.py": "processes",
    "tests/test_device_runs_state.py::test_state_carries_the_candidate_under_test_that_the_resumed_gate_judges_again": "processes",
    "tests/test_device_runs_state.py::test_a_state_without_the_candidates_manifest_says_so_and_the_resumed_gate_drops_it": "processes",
    "tests/test_device_runs_state.py::test_state_carries_the_candidates_that_met_the_bars_which_the_resumed_run_exports": "processes",
    "tests/test_pools.py": "processes",
    "tests/test_hazard_table.py::test_pytest_collects_every_named_test": "processes",
    "tests/test_plant.py::test_the_in_process_twin_runs_without_zenoh": "processes",
    "tests/test_diagnosis_benchmark.py::test_stopping_the_workers_ends_running_cases_at_once": "processes",
    "tests/test_jobs.py::test_bad_queue_and_job_input_is_refused": "processes",
    "tests/test_web_hygiene.py::test_request_body_size_limit": "processes",
    # (as admin, the fuzzer's upload of a loadable ONNX starts a validation child)
    "tests/test_schemathesis.py::test_no_server_errors_and_conformance_as_admin": "processes",
    # slow: more than about 20 twin throws (dataset generation, diagnosis fits, benchmarks) or a
    # wait of 2 s or more on a real-time bound (an E-STOP's confirmation deadline, a frozen runtime)
    "tests/test_diagnosis.py::test_small_blind_benchmark": "slow",
    "tests/test_diagnosis.py::test_server_runs_a_diagnosis_on_stored_throws": "slow",
    "tests/test_diagnosis.py::test_small_benchmark_impact_only_and_power_kinds": "slow",
    "tests/test_diagnosis.py::test_noise_only_dataset_with_a_sub_noise_trajectory_bias_is_no_gap": "slow",
    "tests/test_diagnosis.py::test_pure_noise_is_no_gap_and_release_delay_is_smooth_without_open_flag": "slow",
    "tests/test_diagnosis_encoder.py": "slow",
    "tests/test_estop_without_storage.py": "slow",
    "tests/test_estop_unknown_token.py": "slow",
    "tests/test_diagnosis_rosbag.py::test_bags_uploaded_through_the_api_are_diagnosed": "slow",
    "tests/test_diagnosis_rosbag.py::test_rosbag2_of_another_library_converts_and_diagnoses": "slow",
    "tests/test_drift.py::test_profile_change_mid_run_raises_an_alert_starts_a_diagnosis_and_offers_the_adaptation": "slow",
    "tests/test_estop_isolation.py::test_a_frozen_machines_estops_do_not_delay_another_machines": "slow",
    "tests/test_clean_edges.py::test_unknown_machine_is_404_known_offline_machine_is_503[estop]": "slow",
    "tests/test_clean_edges.py::test_unknown_machine_is_404_known_offline_machine_is_503[abort]": "slow",
    # the training extra (jax, torch): the fine-tuning config's privileged ranges
    "tests/test_adapt.py::test_finetune_config_fixes_the_profiles_effects": "torch",
    "tests/test_wind_training.py::test_the_environment_lands_the_payload_where_the_wind_moves_it": "torch",
    # acceptance tests of the deployed policies (policies/*.onnx): how well they throw
    "tests/test_evaluate.py::test_deployed_2d_policy": "acceptance",
    "tests/test_controller.py::test_robust_3d_throws_with_a_slow_valve_delay": "acceptance",
    "tests/test_preview.py::test_monte_carlo_ellipse": "acceptance",
    "tests/test_jobs.py::test_preview_runs_in_a_worker": "acceptance",
}
"""Tests outside the fast tier by node id prefix, with the marker they get; the comment above each
group states the rule that puts a test there (docs/development.md: test tiers)."""


def _python_argv(args) -> bool:
    """``args`` (Popen's first argument) runs a Python interpreter: Slinger's processes
    (server.site.stack.slinger_command), a policy validation child, ``python -c ...``."""
    argv = [args] if isinstance(args, (str, bytes, os.PathLike)) else list(args)
    if not argv:
        return False
    first = os.fsdecode(argv[0])
    return first == sys.executable or os.path.basename(first).startswith("python") or os.path.basename(first) == "slinger"


_PROCESSES_OF: dict[str, list[str]] = {}
"""Node id of the running fast-tier test -> the Python processes it (or its fixtures) started."""
_running: list[str | None] = [None]


def _record_process(what: str) -> None:
    nodeid = _running[0]
    if nodeid is not None:
        _PROCESSES_OF.setdefault(nodeid, []).append(what)


def _watch_process_starts() -> None:
    """Record every Python child process (subprocess) and multiprocessing process (process pools)
    started while a fast-tier test runs; :func:`_fast_tier_starts_no_processes` fails the test."""
    import multiprocessing.process
    import subprocess

    popen_init = subprocess.Popen.__init__
    process_start = multiprocessing.process.BaseProcess.start

    def init(self, args, *a, **kw):
        if _python_argv(args):
            argv = " ".join(map(os.fsdecode, args)) if isinstance(args, list | tuple) else os.fsdecode(args)
            _record_process(f"subprocess {argv[:160]}")
        popen_init(self, args, *a, **kw)

    def start(self):
        _record_process(f"multiprocessing {type(self).__name__} {self.name}")
        process_start(self)

    subprocess.Popen.__init__ = init  # type: ignore[method-assign]
    multiprocessing.process.BaseProcess.start = start  # type: ignore[method-assign]


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    _running[0] = None if item.get_closest_marker("system") else item.nodeid


@pytest.fixture(autouse=True)
def _fast_tier_starts_no_processes(request):
    """The fast tier's rule, checked: a test without ``system`` starts no Python process (a
    Slinger server, worker, runtime, plant or bridge, a policy validation child, a process pool of
    twin throws), in its body or its fixtures; one that does needs the ``processes`` marker
    (:data:`SLOW_TESTS`). Short commands of other programs (git, sqlite3) are allowed."""
    yield
    started = _PROCESSES_OF.pop(request.node.nodeid, [])
    if started:
        pytest.fail("a fast-tier test started Python processes (mark it 'processes' in tests/conftest.py SLOW_TESTS): "
                    + "; ".join(started[:5]), pytrace=False)


def pytest_collection_modifyitems(config, items) -> None:
    """Mark tests by node id (:data:`SLOW_TESTS`) and by the fixtures they use
    (:data:`FIXTURE_MARKERS`), then add ``system`` to every test with one of :data:`SYSTEM_MARKERS`."""
    for item in items:
        for prefix, marker in SLOW_TESTS.items():
            if item.nodeid.startswith(prefix):
                item.add_marker(marker)
        for fixture, marker in FIXTURE_MARKERS.items():
            if fixture in getattr(item, "fixturenames", ()):
                item.add_marker(marker)
        if any(item.get_closest_marker(m) for m in SYSTEM_MARKERS):
            item.add_marker("system")


@pytest.fixture(scope="session", autouse=True)
def cheap_password_hashes():
    """argon2id at its minimal cost in this process (1 pass, 1 MiB, 1 lane): the hash's cost is
    not what the tests check, and the library's default (64 MiB, 3 passes, 4 lanes; server.accounts.auth)
    costs about 0.2 s of CPU per hash or log-in. Processes that tests start keep the default."""
    from argon2 import PasswordHasher

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("server.accounts.auth._hasher", PasswordHasher(time_cost=1, memory_cost=1024, parallelism=1))
        yield


@pytest.fixture(scope="session")
def fixture_policy(tmp_path_factory) -> Callable[[str], Path]:
    """``fixture_policy(mode)``: the path of a small fixture policy of ``mode`` ("2d" or "3d"; a
    random linear-tanh ONNX with its manifest, tests.fixtures.write_test_policy), written once per
    session. Not a thrower: for tests whose assertions do not depend on how well a policy throws;
    the deployed policies' acceptance tests load policies/*.onnx (docs/development.md)."""
    from tests.fixtures import write_test_policy

    root = tmp_path_factory.mktemp("fixture-policies")
    made: dict[str, Path] = {}

    def path(mode: str) -> Path:
        if mode not in made:
            made[mode] = write_test_policy(root / mode, mode, name=f"fixture-{mode}")
        return made[mode]

    return path


def free_port() -> int:
    """A TCP port that was free a moment ago on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate: Callable[[], object], timeout_s: float = 10.0, what: str = "condition"):
    """Poll ``predicate`` every 50 ms until truthy; return its value or fail the test."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


def machine_key(site_dir: Path, machine_id: str) -> bytes:
    """The machine's command key in ``site_dir`` (as ``slinger certs`` lays it out), made if missing."""
    path = site_dir / "machines" / machine_id / "command.key"
    if not path.is_file():
        write_key(path, new_key())
    return load_key(path)


class FakeRuntime:
    """A runtime stand-in: liveliness token, info and throw queryables, 20 Hz MachineState,
    and, per accepted throw, statuses and a ThrowResult delivered as a query to THROW_RESULT.
    Like the real runtime it checks the server's signatures (command key in ``site_dir``, its own
    epoch), latches E-STOP on an abort until a signed EstopReset, and MACs its results.

    Args:
        endpoint: Zenoh endpoint of the server to connect to.
        machine_id: its machine id.
        refuse: if set, refuse every throw with this reason.
        silent: never answer throw requests (the server must time out).
        deliver: deliver a result after accepting (else the throw stays open).
        cabin_turn_rad: the cabin angle it reports.
        site_dir: the site directory holding (or receiving) the machine's command key.
        hold: accept throws but never finish them (the throw stays running).
        clock_offset_s: its wall clock runs this far off the host's (checks freshness with it and
            reports it as RuntimeInfo.clock_unix_s).
        lease_holder: the server id it obeys from the start (RuntimeInfo.lease_holder).
        undeliverable: RuntimeInfo.undeliverable_results from the start.

    Like the real runtime it publishes its RuntimeInfo on keys.runtime_state at 2 Hz and within one
    state period (50 ms) of a change (runtime.service.RuntimeService.publish_info), unless
    ``publish_info`` is False (an older runtime that only answers queries).

    Set ``frozen = True`` to stand for a stopped (SIGSTOP) runtime: aborts and E-STOP puts are
    neither executed nor answered, and no RuntimeInfo is published (the machine's MachineState,
    which this stand-in publishes too, goes on). ``lease_holder`` (the server id it obeys,
    reported in RuntimeInfo; a signed LeaseRequest takes it when free, held by its sender, or with
    ``takeover``) and ``undeliverable`` (RuntimeInfo.undeliverable_results) may be set; a signed
    ReturnToReady is accepted unless E-STOP is latched (``returns`` lists them).
    """

    def __init__(self, endpoint: str, machine_id: str = "m1", refuse: str | None = None,
                 silent: bool = False, deliver: bool = True, cabin_turn_rad: float = 0.0,
                 policies: list[PolicyInfo] | None = None, site_dir: Path | None = None, hold: bool = False,
                 clock_offset_s: float = 0.0, lease_holder: str | None = None, undeliverable: int = 0,
                 publish_info: bool = True):
        self.machine_id, self.refuse, self.silent, self.deliver = machine_id, refuse, silent, deliver
        self.hold = hold
        self.frozen = False
        self.unanswered: list = []
        self.epoch = int(time.time() * 1000)
        self.key = machine_key(site_dir, machine_id) if site_dir is not None else None
        self.wall_clock = lambda: time.time() + clock_offset_s
        self.verifier = CommandVerifier(self.key, self.epoch, wall_clock=self.wall_clock) if self.key is not None else None
        self.estop_reason: str | None = None
        self.current: tuple[str, str] | None = None  # (throw id, phase) of the running throw
        self.policies = policies or [PolicyInfo(mode="2d", version="fake-2d", sha256="ab" * 32)]
        self.aborts: list[bytes] = []
        self.cabin_turn_rad = cabin_turn_rad
        self.requests: list[ThrowRequest] = []
        self.lease_holder = lease_holder  # set before the queryables exist: the first info query sees it
        self.undeliverable = undeliverable
        self.returns: list[ReturnToReady] = []
        self.acks: list[ResultAck] = []
        self.results: list[ThrowResult] = []
        self._stop = threading.Event()
        self.session = open_session(mode="peer", connect=(endpoint,))
        s = self.session
        self._decls = [
            s.declare_queryable(keys.throw(machine_id), self._on_throw),
            s.declare_queryable(keys.info(machine_id), self._on_info),
            s.declare_queryable(keys.abort(machine_id), self._on_abort),
            s.declare_queryable(keys.estop_reset(machine_id), self._on_estop_reset),
            s.declare_queryable(keys.lease(machine_id), self._on_lease),
            s.declare_queryable(keys.return_to_ready(machine_id), self._on_return_to_ready),
        ]
        self._estop_sub = s.declare_subscriber(keys.estop(machine_id), self._on_estop)
        self._state_pub = s.declare_publisher(keys.state(machine_id))
        self._info_pub = s.declare_publisher(keys.runtime_state(machine_id)) if publish_info else None
        self._info_sent: tuple[RuntimeInfo | None, float] = (None, -1.0)  # (info without its clock, monotonic s)
        self._status_pub = s.declare_publisher(keys.status(machine_id))
        self._token = s.liveliness().declare_token(keys.runtime_alive(machine_id))
        self._threads = [threading.Thread(target=self._publish_states, daemon=True)]
        self._threads[0].start()

    def state(self) -> MachineState:
        return MachineState(machine_id=self.machine_id, stamp_s=time.monotonic(),
                            q=[self.cabin_turn_rad, -0.5, 1.5, 0.2, -1.0, 0.0], qd=[0.0] * 6,
                            gripper_open=False, payload_attached=True, simulated=True)

    def _publish_states(self) -> None:
        while not self._stop.wait(0.05):
            self._state_pub.put(encode(self.state()))
            if not self.frozen:
                self._publish_info()

    def _publish_info(self) -> None:
        """RuntimeInfo on keys.runtime_state if it changed or 0.5 s passed (as the runtime's INFO_PERIOD_S)."""
        if self._info_pub is None:
            return
        info, now = self.info(), time.monotonic()
        bare = info.model_copy(update={"clock_unix_s": None})
        if bare == self._info_sent[0] and now - self._info_sent[1] < 0.5:
            return
        self._info_sent = (bare, now)
        self._info_pub.put(encode(info))

    def info(self) -> RuntimeInfo:
        current = self.current
        latched = self.estop_reason is not None
        return RuntimeInfo(machine_id=self.machine_id, busy=current is not None, machine_online=True, simulated=True,
                           policies=self.policies, epoch=self.epoch, estop_latched=latched,
                           estop_reason=self.estop_reason, ready=not latched and current is None,
                           not_ready_reason="E-STOP latched" if latched else None,
                           throw_id=current[0] if current else None, phase=current[1] if current else None,
                           clock_unix_s=self.wall_clock(), lease_holder=self.lease_holder,
                           undeliverable_results=self.undeliverable)

    def _on_info(self, query) -> None:
        query.reply(keys.info(self.machine_id), encode(self.info()))

    def _abort(self, raw: bytes) -> bytes:
        self.aborts.append(raw)
        req = decode(AbortRequest, raw) if raw else AbortRequest(machine_id=self.machine_id, reason="abort")
        self.estop_reason = req.reason
        aborted = self.current[0] if self.current else None
        return encode(AbortAck(machine_id=self.machine_id, aborted_throw_id=aborted, request_id=req.request_id))

    def _on_abort(self, query) -> None:
        if self.frozen:
            self.unanswered.append(query)  # kept open, unanswered, as by a stopped process
            return
        raw = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(keys.abort(self.machine_id), self._abort(raw))

    def _on_estop(self, sample) -> None:
        """The server's E-STOP put: latch, then the AbortAck on keys.estop_ack (as the runtime)."""
        if self.frozen:
            return
        self.session.put(keys.estop_ack(self.machine_id), self._abort(sample.payload.to_bytes()))

    def _check(self, msg) -> str | None:
        return self.verifier.check(msg) if self.verifier is not None else None

    def _on_estop_reset(self, query) -> None:
        req = decode(EstopReset, query.payload.to_bytes())
        reason = self._check(req)
        if reason is None:
            self.estop_reason = None
        ack = EstopResetAck(machine_id=self.machine_id, reset=reason is None, reason=reason)
        query.reply(keys.estop_reset(self.machine_id), encode(ack))

    def _on_lease(self, query) -> None:
        req = decode(LeaseRequest, query.payload.to_bytes())
        server = req.auth.server if req.auth is not None and req.auth.server is not None else ""
        reason = self._check(req)
        if reason is None and self.lease_holder not in (None, server) and not req.takeover:
            reason = f"machine {self.machine_id} is commanded by server {self.lease_holder}"
        if reason is None:
            self.lease_holder = server
        ack = LeaseAck(machine_id=self.machine_id, granted=reason is None, holder=self.lease_holder, reason=reason)
        query.reply(keys.lease(self.machine_id), encode(ack))

    def _on_return_to_ready(self, query) -> None:
        req = decode(ReturnToReady, query.payload.to_bytes())
        reason = self._check(req) or ("E-STOP latched" if self.estop_reason else None)
        if reason is None:
            self.returns.append(req)
        ack = ReturnToReadyAck(machine_id=self.machine_id, accepted=reason is None, reason=reason)
        query.reply(keys.return_to_ready(self.machine_id), encode(ack))

    def _on_throw(self, query) -> None:
        req = decode(ThrowRequest, query.payload.to_bytes())
        self.requests.append(req)
        if self.silent:
            return
        refuse = self.refuse or self._check(req) or ("E-STOP latched" if self.estop_reason else None)
        accepted = refuse is None
        ack = ThrowAck(throw_id=req.throw_id, accepted=accepted, reason=refuse,
                       policy_version="fake-2d" if accepted else None)
        if accepted:
            self.current = (req.throw_id, "preparing")
        query.reply(keys.throw(self.machine_id), encode(ack))
        if accepted and self.deliver and not self.hold:
            t = threading.Thread(target=self._fly, args=(req,), daemon=True)
            self._threads.append(t)
            t.start()

    def make_result(self, req: ThrowRequest, impact=(8.3, -0.1, 0.0)) -> ThrowResult:
        """A landed result with a small MCAP recording (10 ticks + payload)."""
        rec = TelemetryRecorder()
        for i in range(10):
            q = [self.cabin_turn_rad, -0.5 + 0.01 * i, 1.5, 0.2, 0.0, 0.0]
            rec.record(0.01 * i, q, [0.0] * 6, [0.0] * 4, [0.0] * 4, i > 5, i > 6, "swinging",
                       payload_pos_m=[5.0 + 0.3 * i, -0.1, 3.0 - 0.3 * i], payload_vel_mps=[3.0, 0.0, -3.0])
        rec.event(0.0, "swinging")
        down, cross = impact_errors(req.target_m, impact)
        result = ThrowResult(
            machine_id=self.machine_id, stamp_s=time.monotonic(), throw_id=req.throw_id, mode=req.mode,
            status="landed", target_m=req.target_m, impact_m=list(impact), downrange_error_m=down,
            crossrange_error_m=cross, policy_version="fake-2d", duration_s=3.2,
            telemetry_mcap_b64=base64.b64encode(write_mcap(rec, {"throw_id": req.throw_id})).decode(),
        )
        return self.signed(result)

    def signed(self, result: ThrowResult) -> ThrowResult:
        """``result`` MAC'ed as the real runtime does (unchanged without a key)."""
        if self.key is None:
            return result
        return sign(result, self.key, f"runtime:{self.machine_id}", self.epoch)

    def _fly(self, req: ThrowRequest) -> None:
        for phase in ("preparing", "swinging", "released"):
            time.sleep(0.05)
            self.current = (req.throw_id, phase)
            self._status_pub.put(encode(ThrowStatus(machine_id=self.machine_id, stamp_s=time.monotonic(),
                                                    throw_id=req.throw_id, phase=phase)))
        time.sleep(0.1)
        self.current = None
        self.send_result(self.make_result(req))

    def send_result(self, result: ThrowResult, timeout_s: float = 10.0) -> ResultAck | None:
        """Deliver ``result`` as the runtime's outbox does: a query to THROW_RESULT."""
        self.results.append(result)
        for reply in self.session.get(keys.THROW_RESULT, payload=encode(result), timeout=timeout_s):
            if reply.ok is not None:
                ack = decode(ResultAck, reply.ok.payload.to_bytes())
                self.acks.append(ack)
                return ack
        return None

    def close(self) -> None:
        """Stop publishing, let in-flight throws finish (bounded), undeclare, close the session."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=12.0)
        self._token.undeclare()
        self._estop_sub.undeclare()

        for d in self._decls:
            d.undeclare()
        self.session.close()


PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
"""The local PostgreSQL (trust auth) whose admin connection makes throwaway databases."""


@pytest.fixture
def pg_url() -> Iterator[str]:
    """The URL of a fresh, empty PostgreSQL database on 127.0.0.1:5432, dropped (forced) after
    the test; the test is skipped when PostgreSQL is unreachable."""
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT", connect_args={"connect_timeout": 3})
    name = f"slinger_test_{uuid.uuid4().hex[:12]}"
    try:
        with admin.connect() as conn:
            conn.execute(text(f'CREATE DATABASE "{name}"'))
    except OperationalError as e:
        admin.dispose()
        pytest.skip(f"PostgreSQL not reachable at 127.0.0.1:5432: {e.orig}")
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    finally:
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.fixture
def zenoh_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def settings(tmp_path: Path, zenoh_endpoint: str):
    """Server settings: SQLite in tmp (migrated by the app), no 3D view, short query timeout;
    the preview gate off (tests of other parts; tests/test_control_chain.py switches it on); jobs
    run inside the test process (``immediate``; tests/test_jobs.py runs real workers); a policy
    validation of 256 observations without twin throws (tests/test_policy_validation.py runs
    the full one)."""
    from server.config import Settings

    return Settings(data_dir=tmp_path / "var", zenoh_listen=[zenoh_endpoint], viser_enabled=False,
                    query_timeout_s=2.0, auto_migrate=True, require_preview=False, job_queue_url="immediate",
                    validation_observations=256, validation_distances=0)


ADMIN = ("admin", "admin-pass-1")
"""User name and password of the admin the test fixtures create."""


def add_user(sessions, username: str, password: str, role: str) -> None:
    """Create a user straight in the database (``sessions``: the app's session factory)."""
    from server.accounts.auth import create_user

    with sessions.begin() as db:
        create_user(db, username, password, role)


def serving(base_url: str) -> bool:
    """The server at ``base_url`` answers GET /api/health with 200 (False while it does not)."""
    import httpx

    try:
        return httpx.get(f"{base_url}/api/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def login(client, username: str, password: str) -> None:
    """Log ``client`` (TestClient or httpx.Client) in; the session cookie stays in the client."""
    r = client.post("/api/auth/login", json={"username": username, "password": password})
    assert r.status_code == 200, r.text


@pytest.fixture
def client(settings) -> Iterator:
    """A TestClient of the app, logged in as an admin; the lifespan (migrations, Zenoh, fleet)
    runs inside. ``client.cookies.clear()`` logs it out."""
    from fastapi.testclient import TestClient

    from server.app import create_app

    with TestClient(create_app(settings)) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        yield c


@pytest.fixture
def fake_runtime_factory(zenoh_endpoint: str, settings) -> Iterator[Callable[..., FakeRuntime]]:
    made: list[FakeRuntime] = []

    def make(**kwargs) -> FakeRuntime:
        kwargs.setdefault("site_dir", settings.resolved_site_dir)
        rt = FakeRuntime(zenoh_endpoint, **kwargs)
        made.append(rt)
        return rt

    yield make
    for rt in made:
        try:
            rt.close()
        except Exception:
            pass


@pytest.fixture
def throw_count(settings) -> Callable[[], int]:
    """Number of rows in the throws table, read straight from the database."""
    from server.db.models import Throw

    engine = create_engine(settings.database_url)

    def count() -> int:
        with engine.connect() as conn:
            return conn.scalar(select(func.count()).select_from(Throw))

    yield count
    engine.dispose()


def wait_online(client, machine_id: str = "m1", online: bool = True, timeout_s: float = 10.0) -> dict:
    """Poll GET /api/machines until ``machine_id`` has the given presence (and a state)."""

    def check():
        for m in client.get("/api/machines").json():
            if m["id"] == machine_id and m["online"] is online and (not online or m["cabin_turn_rad"] is not None):
                return m
        return None

    return wait_for(check, timeout_s, f"{machine_id} online={online}")


def add_user_cli(up: "SlingerUp", username: str, password: str, role: str) -> None:
    """Add a user to a running ``slinger up`` through the admin API."""
    r = up.http.post("/api/users", json={"username": username, "password": password, "role": role})
    assert r.status_code == 201, r.text


class SlingerUp:
    """``slinger up`` as a subprocess with the test policy and free ports (context manager).

    On exit it sends SIGINT (what Ctrl-C does) and waits; :attr:`returncode` and :attr:`output`
    are set afterwards. Attributes: base_url, viser_port, data_dir.
    """

    def __init__(self, tmp_path: Path, machines: int = 1, create_admin: bool = True, real_policies: bool = False,
                 env: dict[str, str] | None = None, args: tuple[str, ...] = ()):
        """real_policies: run the repository's deployed policies (both modes) with the runtime's release
        check ON, as the main job does, instead of the non-throwing test policy. env: more
        environment variables for the stack (settings as SLINGER_*). args: more options of `slinger up`."""
        from server.site.stack import slinger_command
        from tests.fixtures import write_test_policy

        self.env = None
        if real_policies:
            extra = []
            self.env = {k: v for k, v in os.environ.items() if k != "SLINGER_RELEASE_CHECK_RADIUS_M"}
        else:
            policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
            # no 3D runtime policy (a missing file keeps the repo's throw3d.onnx out)
            extra = ["--policy-2d", str(policy), "--policy-3d", str(tmp_path / "no-3d-policy.onnx")]
        if env:
            self.env = {**(self.env if self.env is not None else os.environ), **env}
        self.port, self.viser_port, zport = free_port(), free_port(), free_port()
        self.data_dir = tmp_path / "var"
        self.base_url = f"http://127.0.0.1:{self.port}"
        self._log_path = tmp_path / "up.log"
        self.argv = slinger_command(
            "up", "--data-dir", str(self.data_dir), "--machines", str(machines),
            "--port", str(self.port), "--zenoh-port", str(zport), "--viser-port", str(self.viser_port), *extra, *args)
        self.cwd = tmp_path
        self.create_admin = create_admin
        self._http = None
        self.returncode: int | None = None
        self.output = ""

    def __enter__(self) -> "SlingerUp":
        import subprocess

        if self.create_admin:  # as an operator would: slinger user add --admin
            from server.site.stack import slinger_command

            subprocess.run(slinger_command("user", "add", "--admin", "--password", ADMIN[1], "--data-dir",
                                       str(self.data_dir)), check=True, capture_output=True, timeout=60,
                           cwd=self.cwd)
        self._log = open(self._log_path, "wb")
        self.proc = subprocess.Popen(self.argv, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True, cwd=self.cwd, env=self.env)
        return self

    def log_text(self) -> str:
        return self._log_path.read_text(errors="replace")

    @property
    def http(self):
        """An httpx.Client on the server, logged in as the admin (made on first use)."""
        import httpx

        if self._http is None:
            wait_for(lambda: serving(self.base_url), 60, "slinger up serving HTTP")
            self._http = httpx.Client(base_url=self.base_url, timeout=10)
            login(self._http, *ADMIN)
        return self._http

    def wait_machine_online(self, machine_id: str = "m1", timeout_s: float = 90.0) -> dict:
        import httpx

        def online():
            if self.proc.poll() is not None:
                pytest.fail(f"slinger up exited early:\n{self._log_path.read_text()[-3000:]}")
            try:
                if self.proc.poll() is None and self._http is None:
                    self.http  # noqa: B018 (logs in once the server answers)
                ms = self.http.get("/api/machines", timeout=2).json()
            except httpx.HTTPError:
                return None
            # online, its state heard and its RuntimeInfo answered (a query that timed out on a
            # loaded host lists the machine online with no policies and busy None)
            return next((m for m in ms if m["id"] == machine_id and m["online"]
                         and m["cabin_turn_rad"] is not None and m["busy"] is not None), None)

        return wait_for(online, timeout_s, f"slinger up: {machine_id} online")

    def __exit__(self, *exc) -> None:
        import os
        import signal
        import subprocess

        if self._http is not None:
            self._http.close()
        try:
            if self.proc.poll() is None:
                os.kill(self.proc.pid, signal.SIGINT)
            self.returncode = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.returncode = self.proc.wait(timeout=5)
        finally:
            self._log.close()
            self.output = self._log_path.read_text(errors="replace")
