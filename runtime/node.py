"""The runtime process (one per machine): policies + controller + throw executor behind Zenoh.

Wiring (keys in runtime/protocol/README.md):

* subscribes keys.state(id) and keys.impact(id) -> runtime.service.RuntimeService;
* publishes keys.valve_cmd (every state tick), keys.gripper_cmd (on change), keys.status (phase
  changes), keys.runtime_state (RuntimeInfo, 2 Hz and on change);
* subscribes keys.estop (the server's E-STOP put: AbortRequest, latches E-STOP) and publishes
  its AbortAck on keys.estop_ack once the latch is on disk (``--state-dir``, default
  ``<outbox-dir>-state``: runtime.estop_latch; a latch there at start starts the runtime latched);
* queryables keys.throw (ThrowRequest -> ThrowAck), keys.abort (AbortRequest -> AbortAck,
  latches E-STOP), keys.estop_reset (EstopReset -> EstopResetAck), keys.return_to_ready
  (ReturnToReady -> ReturnToReadyAck, runtime.recovery), keys.info (-> RuntimeInfo);
* exclusive claim (runtime.zenoh_session.claim_exclusive): at start it declares a claim token
  keys.runtime_claim(id, claim) and listens 1.5 s; if another runtime holds keys.runtime_alive(id)
  or claimed earlier (two started at once), it exits with code 3 ("machine m1 already has a
  runtime"); else it declares the alive token and picks its epoch = int(time.time() * 1000)
  (commands for another epoch are refused);
* signed commands: ``--command-key PATH`` (64 hex digits, ``slinger certs`` writes
  ``<site_dir>/machines/<id>/command.key``). Without it every throw, E-STOP reset and policy
  offer is refused "no command key configured" (aborts still work);
* release check (runtime.release_check, runtime.executor): ``--release-check-radius M`` (default
  3.0 m; ``off`` switches it off). If it is on and MuJoCo (the ``release-check`` extra) or the
  machine's model cannot be loaded, the runtime says so at start-up and refuses every throw with
  the reason;
* fault injection for tests only: ``SLINGER_CLOCK_OFFSET_S`` runs this runtime's wall clock
  (command freshness, RuntimeInfo.clock_unix_s) that many seconds off the host's;
* warm-up: throws are refused "runtime warming up" until each policy, the release check and the
  telemetry writer ran once (RuntimeService.warm_up), E-STOPs work from the start;
* a watchdog thread (every 50 ms): no valid state for 0.2 s during a throw -> failed; a gap of
  more than 0.2 s between the runtime's own ticks (it stalled) fails the throw and refuses what
  was queued meanwhile (runtime.service: finality);
* the outbox delivers finished ThrowResults to keys.THROW_RESULT (every server's queryable: the
  issuing one stores) until a server acks them stored; it survives a full disk and sets aside
  results servers keep refusing (runtime.outbox);
* one writer per machine: queryable keys.lease (LeaseRequest -> LeaseAck); every signed command
  renews or takes the lease of its server, another server's commands are refused
  (runtime.service);
* queryable keys.policy_offer (PolicyOffer -> PolicyOfferAck): runtime.policy_update fetches,
  checks and installs offered policy versions between throws, publishing keys.policy_status.

Entry points: ``build_parser(parser)`` and ``run(args)`` (used by ``slinger runtime``), and
``python -m runtime.node --machine-id m1 --policy-2d policies/p2d.onnx --listen tcp/0.0.0.0:7447``.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from pathlib import Path

import zenoh

from runtime.command_auth import CommandVerifier, load_key
from runtime.controller import JointVelocityController
from runtime.entrypoint import module_main, stop_on_signals
from runtime.estop_latch import EstopLatchFile
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.heap import HeapTrimmer, bound_heap
from runtime.outbox import Outbox, zenoh_deliverer
from runtime.policy import PolicyError, PolicyRunner
from runtime.policy_update import PolicyUpdater, zenoh_fetcher
from runtime.protocol import keys
from runtime.protocol.messages import encode
from runtime.release_check import DEFAULT_RADIUS_M, ReleaseCheck, parse_radius
from runtime.service import LINK_TIMEOUT_S, RuntimeService
from runtime.zenoh_session import Claimed, add_session_arguments, claim_exclusive, open_session, session_options

EXIT_ALREADY_CLAIMED = 3
"""Exit code when another process already holds the machine id's liveliness token."""

log = logging.getLogger(__name__)

WATCHDOG_PERIOD_S = 0.05


CLOCK_OFFSET_ENV = "SLINGER_CLOCK_OFFSET_S"
"""Fault injection for tests only: this runtime's wall clock runs this many seconds off the
host's (a host whose time sync failed), without touching the system clock."""


def declare_publishers(session: zenoh.Session, machine_id: str) -> dict[str, zenoh.Publisher]:
    """The runtime's publishers, by key (runtime.protocol.keys), with their Zenoh QoS.

    Zenoh publishers drop a sample when the link's transmission queue of their priority is full
    (congestion control DROP, its default for publications) and batch samples (express off). That
    suits the 100 Hz streams, where each sample supersedes the last. It does not suit the messages
    sent once: a GripperCommand goes out only when the command changes (runtime.service), so a
    dropped opening leaves the payload in the gripper (hazard RT14, docs/safety.md), and the E-STOP's
    AbortAck confirms a stop. These are sent express on priority lanes of their own, so that the
    100 Hz valve stream and the status traffic cannot fill their queue: the GripperCommand on
    INTERACTIVE_HIGH, the AbortAck on REAL_TIME (the lane of the server's E-STOP puts,
    server.fleet.estop). Still DROP: BLOCK would park the control loop on a dead link.
    """
    plain = (keys.valve_cmd(machine_id), keys.status(machine_id), keys.runtime_state(machine_id))
    pubs = {k: session.declare_publisher(k) for k in plain}
    pubs[keys.gripper_cmd(machine_id)] = session.declare_publisher(
        keys.gripper_cmd(machine_id), priority=zenoh.Priority.INTERACTIVE_HIGH, express=True)
    pubs[keys.estop_ack(machine_id)] = session.declare_publisher(
        keys.estop_ack(machine_id), priority=zenoh.Priority.REAL_TIME, express=True)
    return pubs


def offset_clock(offset_text: str | None):
    """The runtime's wall clock: time.time, shifted by ``offset_text`` seconds when given
    (CLOCK_OFFSET_ENV; logged as a warning).

    Raises:
        ValueError: ``offset_text`` is not a finite number.
    """
    if not offset_text:
        return time.time
    offset_s = float(offset_text)
    if offset_s != offset_s or abs(offset_s) == float("inf"):
        raise ValueError(f"{CLOCK_OFFSET_ENV} must be a finite number of seconds, got {offset_text!r}")
    log.warning("%s=%s: this runtime's wall clock runs %+.1f s off the host's (fault injection)",
                CLOCK_OFFSET_ENV, offset_text, offset_s)
    return lambda: time.time() + offset_s


def default_outbox_dir(machine_id: str) -> Path:
    """~/.slinger/outbox/<machine_id>"""
    return Path.home() / ".slinger" / "outbox" / machine_id


def build_parser(parser: argparse.ArgumentParser) -> None:
    """Add the runtime's arguments to ``parser``."""
    parser.add_argument("--machine-id", required=True, help="machine id, [A-Za-z0-9_-]{1,64}")
    parser.add_argument("--policy-2d", type=Path, default=None, help="2D policy ONNX file (manifest beside it)")
    parser.add_argument("--policy-3d", type=Path, default=None, help="3D policy ONNX file (manifest beside it)")
    add_session_arguments(parser)
    parser.add_argument("--command-key", type=Path, default=None,
                        help="this machine's command key file (64 hex digits); without it every throw, E-STOP reset "
                             "and policy offer is refused")
    parser.add_argument("--outbox-dir", type=Path, default=None, help="durable outbox directory (default ~/.slinger/outbox/<machine-id>)")
    parser.add_argument("--state-dir", type=Path, default=None,
                        help="where the E-STOP latch is kept across restarts (default: <outbox-dir>-state)")
    parser.add_argument("--policy-dir", type=Path, default=None, help="where promoted policy files are kept (default: <outbox-dir>-policies)")
    parser.add_argument("--link-timeout", type=float, default=LINK_TIMEOUT_S, help="seconds without machine state that fail a throw")
    parser.add_argument("--release-check-radius", type=release_check_radius, default=DEFAULT_RADIUS_M,
                        help="hold a release whose predicted impact is farther than this from the target, m, or 'off' "
                             f"(default {DEFAULT_RADIUS_M} m; needs MuJoCo: the 'release-check' extra)")


def release_check_radius(text) -> float | None:
    """--release-check-radius: runtime.release_check.parse_radius for argparse.

    Raises:
        argparse.ArgumentTypeError: what parse_radius refuses.
    """
    try:
        return parse_radius(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def load_policies(args: argparse.Namespace) -> dict[str, PolicyRunner]:
    """Load --policy-2d / --policy-3d.

    Raises:
        PolicyError: a policy does not load or check, sits under the wrong mode, or none given.
    """
    policies = {}
    for mode, path in (("2d", args.policy_2d), ("3d", args.policy_3d)):
        if path is None:
            continue
        runner = PolicyRunner.load(path)
        if runner.mode != mode:
            raise PolicyError(f"{path} is a {runner.mode} policy, given as --policy-{mode}")
        policies[mode] = runner
        log.info("%s policy %s (sha256 %s…)", mode, runner.version, runner.sha256[:12])
    if not policies:
        raise PolicyError("give at least one of --policy-2d, --policy-3d")
    return policies


def watchdog_tick(service: RuntimeService, updater: PolicyUpdater, trimmer: HeapTrimmer) -> None:
    """The runtime's housekeeping every WATCHDOG_PERIOD_S: the link watchdog, a policy update
    that waits for the machine to be idle, the RuntimeInfo repeat and, while no throw or return
    runs (:meth:`RuntimeService.idle`), the heap trim when due (runtime.heap: a trim holds the
    heap's locks for a few ms, which no 10 ms control step should wait for; a throw accepted in
    the instant between the check and the trim may see its first step wait that long)."""
    service.check_watchdog()
    updater.apply_pending(service.executor, service.lock)
    service.publish_info()
    if service.idle():
        trimmer.tick()


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run the runtime until SIGINT/SIGTERM (or ``stop`` is set). Returns the exit code
    (2: bad arguments, policy or command key; 3: the machine already has a runtime)."""
    try:
        machine_id = keys.validate_machine_id(args.machine_id)
        policies = load_policies(args)
        key = load_key(args.command_key) if args.command_key else None
        zenoh_opts = session_options(args, f"runtime-{machine_id}")
        radius = release_check_radius(getattr(args, "release_check_radius", DEFAULT_RADIUS_M))
        wall_clock = offset_clock(os.environ.get(CLOCK_OFFSET_ENV))
    except (ValueError, OSError, PolicyError, argparse.ArgumentTypeError) as e:
        log.error("cannot start runtime: %s", e)
        return 2
    if key is None:
        log.warning("no command key configured (--command-key): every throw, E-STOP reset and policy offer will be refused")
    stop = stop_on_signals(stop)
    bound_heap()  # before Zenoh's and the policies' threads start: fewer arenas, large blocks mapped (runtime.heap)
    trimmer = HeapTrimmer()
    outbox_dir = args.outbox_dir or default_outbox_dir(machine_id)
    try:
        latch = EstopLatchFile(getattr(args, "state_dir", None) or Path(f"{outbox_dir}-state"), machine_id)
    except OSError as e:
        log.error("cannot start runtime: state directory: %s", e)
        return 2
    if radius is None:
        log.warning("release check off (--release-check-radius off): releases are not checked")
    check = ReleaseCheck.load() if radius is not None else None  # the executor logs why if it cannot
    executor = ThrowExecutor(policies, JointVelocityController(), ExecutorConfig(release_check_radius_m=radius),
                             release_check=check)

    with open_session(**zenoh_opts) as session:
        try:
            token, claim_token = claim_exclusive(session, keys.runtime_alive(machine_id),
                                                 lambda c: keys.runtime_claim(machine_id, c))
        except Claimed as e:
            log.error("machine %s already has a runtime (%s): not starting a second one", machine_id, e)
            return EXIT_ALREADY_CLAIMED
        epoch = int(time.time() * 1000)
        verifier = CommandVerifier(key, epoch, wall_clock=wall_clock) if key is not None else None
        pubs = declare_publishers(session, machine_id)
        outbox = Outbox(outbox_dir, zenoh_deliverer(session))
        status_pub = session.declare_publisher(keys.policy_status(machine_id))
        service = RuntimeService(machine_id, executor, lambda k, data: pubs[k].put(data), outbox.put,
                                 verifier=verifier, link_timeout_s=args.link_timeout, epoch=epoch, latch=latch,
                                 wall_clock=wall_clock, warm_up=True, undeliverable=lambda: outbox.undeliverable)
        updater = PolicyUpdater(machine_id, getattr(args, "policy_dir", None) or Path(f"{outbox_dir}-policies"),
                                zenoh_fetcher(session), lambda msg: status_pub.put(encode(msg)), authorize=service.authorize)

        def reply(handler):
            def on_query(query):
                payload = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    query.reply(query.key_expr, handler(payload))
                except Exception:
                    log.exception("query on %s failed", query.key_expr)

            return on_query

        entities = [
            session.declare_subscriber(keys.state(machine_id), lambda s: service.on_state(s.payload.to_bytes())),
            session.declare_subscriber(keys.impact(machine_id), lambda s: service.on_impact(s.payload.to_bytes())),
            session.declare_subscriber(keys.estop(machine_id), lambda s: service.on_estop(s.payload.to_bytes())),
            session.declare_queryable(keys.throw(machine_id), reply(service.handle_throw)),
            session.declare_queryable(keys.abort(machine_id), reply(service.handle_abort)),
            session.declare_queryable(keys.estop_reset(machine_id), reply(service.handle_estop_reset)),
            session.declare_queryable(keys.return_to_ready(machine_id), reply(service.handle_return_to_ready)),
            session.declare_queryable(keys.info(machine_id), reply(lambda _p: service.handle_info())),
            session.declare_queryable(keys.policy_offer(machine_id), reply(updater.handle_offer)),
            session.declare_queryable(keys.lease(machine_id), reply(service.handle_lease)),
            status_pub,
            token,
            claim_token,
            *pubs.values(),
        ]
        outbox.start()
        service.warm_up()  # policies, release check, telemetry writer: throws refused until done
        log.info("runtime %s up: epoch %d, policies %s, outbox %s", machine_id, epoch, sorted(policies), outbox_dir)
        try:
            while not stop.wait(WATCHDOG_PERIOD_S):
                watchdog_tick(service, updater, trimmer)
        finally:
            service.shutdown()
            outbox.stop()
            for entity in entities:
                entity.undeclare()
    log.info("runtime %s stopped", machine_id)
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main('python -m runtime.node', "Slinger runtime (one per machine)", build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
