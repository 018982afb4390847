"""Wire messages (JSON, pydantic v2). Each carries ``schema_version``; machine-interface
messages also carry the ``machine_id`` and a monotonic timestamp ``stamp_s`` (seconds on the
sender's monotonic clock, :func:`time.monotonic`).

Vectors of joint values follow ``runtime.machine.JOINT_NAMES`` (6 joints) or
``ACTIVE_JOINTS`` (4 joints); positions are in the machine frame (docs/architecture.md), metres.

Non-finite numbers (NaN, inf) are rejected at validation: a malformed or NaN message raises
:class:`pydantic.ValidationError` in :func:`decode`, which callers log and drop.
"""

from __future__ import annotations

import math
from typing import Annotated, Final, Literal, TypeVar

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from runtime.protocol.keys import machine_id_of, validate_machine_id

SCHEMA_VERSION: Final = 1

Mode = Literal["2d", "3d"]


def _finite(values: list[float]) -> list[float]:
    for v in values:
        if not math.isfinite(v):
            raise ValueError("non-finite value")
    return values


def _unit_interval(values: list[float]) -> list[float]:
    if any(abs(v) > 1.0 for v in values):
        raise ValueError("valve command outside [-1, 1]")
    return values


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3), AfterValidator(_finite)]
Vec4 = Annotated[list[float], Field(min_length=4, max_length=4), AfterValidator(_finite)]
Vec6 = Annotated[list[float], Field(min_length=6, max_length=6), AfterValidator(_finite)]
MachineId = Annotated[str, AfterValidator(validate_machine_id)]


class Message(BaseModel):
    """Base of all wire messages: strict about unknown fields and the schema version."""

    model_config = ConfigDict(extra="forbid")
    schema_version: Literal[1] = SCHEMA_VERSION


class Stamped(Message):
    """A message of the machine interface: who sent it and when (monotonic seconds)."""

    machine_id: MachineId
    stamp_s: float = Field(allow_inf_nan=False)


class MachineState(Stamped):
    """Joint state of the machine, published at 100 Hz by the hardware bridge or the plant.

    Attributes:
        q: (6,) joint positions, rad / m; the passive joints come from the gripper IMU.
        qd: (6,) joint velocities, rad/s / m/s.
        gripper_open: the gripper is physically open (payload free).
        payload_attached: a payload is held by the gripper.
        payload_pos_m / payload_vel_mps: (3,) payload state when the machine can observe it
            (the simulated machine always; real hardware only with a tracker), else None.
        simulated: True for the simulated machine (sim_twin plant), False for hardware.
        reset_count: simulated machine only: how many SimReset requests it has applied since
            it started (used by the twin's evaluation loop); None on hardware.
        machine_fault: why the machine cannot be commanded now (e.g. the simulated machine
            "behind real time by 150 ms"), or None. The runtime refuses throws with this reason
            and fails a running one.
        watchdog_trips: how often the machine's valve watchdog has put the valves neutral since
            it started (no fresh ValveCommand for its bound), or None when the machine does not
            report it. A running throw during which it grows fails (runtime.executor: finality).
    """

    q: Vec6
    qd: Vec6
    gripper_open: bool
    payload_attached: bool
    payload_pos_m: Vec3 | None = None
    payload_vel_mps: Vec3 | None = None
    simulated: bool = False
    reset_count: Annotated[int, Field(ge=0)] | None = None
    machine_fault: Annotated[str, Field(max_length=200)] | None = None
    watchdog_trips: Annotated[int, Field(ge=0)] | None = None


class ValveCommand(Stamped):
    """Normalised valve commands of the four active joints, each in [-1, 1] (100 Hz).

    Attributes:
        epoch: the sending runtime's claim epoch (ms since the Unix epoch at its start), or None
            from senders without a claim (tests, tools). The machine follows only the newest
            epoch it has seen.
    """

    u: Annotated[Vec4, AfterValidator(_unit_interval)]
    epoch: Annotated[int, Field(ge=0)] | None = None


class GripperCommand(Stamped):
    """Open (release the payload) or close (grasp a new payload) the gripper."""

    open: bool


STALE_COMMAND_S = 0.2
"""A machine (the simulated machine's plant, the ROS 2 bridge) drops a non-neutral ValveCommand or an
opening GripperCommand whose stamp (the stamp of the MachineState it answers, on the machine's
monotonic clock, which the runtime shares) is older than this, s: it was queued somewhere (a
stalled runtime or bridge) and would move the arm or release the payload late. CHOSEN 0.2 s: the
runtime's own bound for stale states and its link timeout; a healthy round trip (state out,
command back) takes milliseconds."""


def stale_motion(msg: ValveCommand | GripperCommand, now_s: float) -> bool:
    """True if ``msg`` moves the machine (a ValveCommand with a non-zero valve, an opening
    GripperCommand) and answers a state older than STALE_COMMAND_S at ``now_s`` (monotonic, s).
    Neutral valves and a closing gripper are never stale: they only stop or hold."""
    moves = any(msg.u) if isinstance(msg, ValveCommand) else msg.open
    return bool(moves) and now_s - msg.stamp_s > STALE_COMMAND_S


class SimReset(Stamped):
    """Simulated machine only: re-initialise to a collision-free pose with a fresh payload.

    Stands for the operator picking up a new payload between throws (the paper's evaluation
    re-initialises the arm at random collision-free poses, Sec. IV-A). Real hardware ignores it.

    Attributes:
        q_active: (4,) pose to start from, or None for a random collision-free pose.
        seed: seed of the random pose, for reproducible evaluations.
    """

    q_active: Vec4 | None = None
    seed: int | None = None


class ImpactReport(Stamped):
    """The payload's first ground contact, measured by the machine (the plant computes it;
    on hardware an external tracker would)."""

    impact_pos_m: Vec3
    opening_stamp_s: float
    impact_stamp_s: float
    release_pos_m: Vec3
    release_vel_mps: Vec3


class CommandAuth(Message):
    """Who asked for a command and the server's MAC over it (see runtime/command_auth.py).

    Attributes:
        user: the requesting user (server side) or "runtime:<id>" for runtime results.
        issued_unix_s: the signer's wall clock (Unix seconds) when it signed.
        nonce: 32 hex digits, fresh per message (replay protection).
        epoch: the runtime claim the command addresses (RuntimeInfo.epoch).
        server: the signing server's identity (server.fleet.command_signer: SLINGER_SERVER_ID, else
            its host name and site directory), or None (results; servers that name none, which
            the runtime treats as one unnamed server). The runtime leases itself to one server
            at a time (runtime.service: one writer per machine); it is covered by the MAC.
        mac: 64 hex digits, HMAC-SHA256 with the machine's command key over the canonical JSON
            of the whole message with ``mac`` = "" (command_auth.canonical_bytes).
    """

    user: Annotated[str, Field(min_length=1, max_length=64)]
    issued_unix_s: float = Field(allow_inf_nan=False)
    nonce: Annotated[str, Field(pattern=r"^[0-9a-f]{32}$")]
    epoch: Annotated[int, Field(ge=0)]
    server: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.:@-]{1,64}$")] | None = None
    mac: Annotated[str, Field(pattern=r"^([0-9a-f]{64})?$")] = ""


class ThrowRequest(Message):
    """Server -> runtime: throw at ``target_m`` (machine frame, m) in ``mode``; must be signed
    (``auth``) for the runtime to accept it."""

    throw_id: Annotated[str, Field(min_length=1, max_length=64)]
    machine_id: MachineId
    mode: Mode
    target_m: Vec3
    auth: CommandAuth | None = None


class ThrowAck(Message):
    """Runtime -> server reply to a ThrowRequest: accepted, or the reason it was refused."""

    throw_id: str
    accepted: bool
    reason: str | None = None
    policy_version: str | None = None
    policy_sha256: str | None = None
    """SHA-256 of the ONNX file of the policy that will run the throw (the version's identity)."""


ABORT_REASON_CHARS = 200
"""The longest AbortRequest reason, characters (senders cut a longer one: a stop is never refused for it)."""


class AbortRequest(Message):
    """Server -> runtime: stop now (valves to neutral) and latch E-STOP until a signed
    EstopReset. Honoured even unsigned (stopping is always safe); ``auth`` names who asked.
    Sent as a put on keys.estop (the server's E-STOP path) or a query on keys.abort.

    Attributes:
        request_id: the sender's id of this stop (repeated puts of one stop carry the same id);
            echoed in the AbortAck on keys.estop_ack. None on the query path.
    """

    machine_id: MachineId
    reason: Annotated[str, Field(max_length=ABORT_REASON_CHARS)] = "operator abort"
    request_id: Annotated[str, Field(pattern=r"^[0-9a-f]{1,64}$")] | None = None
    auth: CommandAuth | None = None


class AbortAck(Message):
    """Runtime -> server: the stop is done (valves neutral) and the latch is on disk.

    Attributes:
        aborted_throw_id: the throw it ended, or None when none ran.
        request_id: the AbortRequest's ``request_id`` (None on the query path).
        latch_persisted: the latch was written to the runtime's state directory (False: it
            could not be, the latch holds in memory only; the runtime logs why).
    """

    machine_id: MachineId
    aborted_throw_id: str | None = None
    request_id: str | None = None
    latch_persisted: bool = True


class EstopReset(Message):
    """Server -> runtime (query keys.estop_reset): release a latched E-STOP; must be signed."""

    machine_id: MachineId
    auth: CommandAuth | None = None


class EstopResetAck(Message):
    """Runtime -> server: ``reset`` True when the latch is released (or was not latched),
    else False with the ``reason`` (unsigned, bad signature, stale, ...)."""

    machine_id: MachineId
    reset: bool
    reason: str | None = None


class ReturnToReady(Message):
    """Server -> runtime (query keys.return_to_ready): drive the arm back to the ready pose
    (runtime.recovery); must be signed. Refused while E-STOP is latched, a throw runs, the machine
    is offline or faulted."""

    machine_id: MachineId
    auth: CommandAuth | None = None


class ReturnToReadyAck(Message):
    """Runtime -> server: ``accepted`` True when the arm started moving to the ready pose, else
    False with the ``reason`` (unsigned, E-STOP latched, throw running, ...)."""

    machine_id: MachineId
    accepted: bool
    reason: str | None = None


ThrowPhase = Literal["preparing", "swinging", "released", "landed", "failed", "aborted"]


class ThrowStatus(Stamped):
    """Runtime -> server: phase changes of a throw."""

    throw_id: str
    phase: ThrowPhase
    detail: str | None = None


class PolicyInfo(Message):
    """What a runtime runs for one mode: the policy version (name) and its SHA-256."""

    mode: Mode
    version: str
    sha256: str


class RuntimeInfo(Message):
    """What a runtime is and can do now (queryable keys.info; published on keys.runtime_state
    at 2 Hz and on every change).

    Attributes:
        epoch: the runtime's claim epoch (ms since the Unix epoch at its start); commands must
            carry it in ``auth.epoch``.
        estop_latched / estop_reason: E-STOP is latched (valves neutral, throws refused) and why.
        ready: a throw would be accepted now (for some mode with a policy); else
            ``not_ready_reason`` says why ("E-STOP latched", "machine offline", the machine's
            fault such as "behind real time by 150 ms", ...).
        phase / throw_id: the running throw's phase and id, or None when idle.
        recovery: the recovery action the runtime offers now ("return_to_ready" when it is not
            ready because of its pose: outside the envelope or a joint at its end), else None.
        returning: a return to the ready pose runs; ``return_progress`` 0..1 (5 % steps);
            ``return_result`` how the last one ended ("reached the ready pose",
            "failed: ...", "stopped: ..."), None before the first.
        clock_unix_s: the runtime host's wall clock (Unix s) when this was sent; the server
            measures the clock offset from it and signs commands in the runtime's time
            (freshness checks then hold under clock drift between hosts). None: not reported.
        lease_holder: the server that commands this machine now (one writer per machine;
            ``CommandAuth.server``, "" for an unnamed one), None while no lease is held.
        undeliverable_results: throw results the outbox set aside after servers refused them
            repeatedly (kept in the outbox's ``undeliverable/``; runtime.outbox).
    """

    machine_id: MachineId
    busy: bool
    policies: list[PolicyInfo]
    machine_online: bool
    simulated: bool
    epoch: Annotated[int, Field(ge=0)] = 0
    estop_latched: bool = False
    estop_reason: str | None = None
    ready: bool = False
    not_ready_reason: str | None = None
    phase: ThrowPhase | None = None
    throw_id: str | None = None
    recovery: Literal["return_to_ready"] | None = None
    returning: bool = False
    return_progress: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    return_result: Annotated[str, Field(max_length=200)] | None = None
    clock_unix_s: float | None = Field(default=None, allow_inf_nan=False)
    lease_holder: Annotated[str, Field(max_length=64)] | None = None
    undeliverable_results: Annotated[int, Field(ge=0)] = 0


class ThrowResult(Stamped):
    """Runtime -> server: the outcome of one throw with its telemetry (MCAP bytes, base64).

    Attributes:
        status: ``landed`` (released, flew and hit the ground), ``failed`` (collision, joint
            limit, timeout, lost link, bad state) or ``aborted``.
        impact_m: (3,) first ground contact of the payload, or None.
        downrange_error_m / crossrange_error_m: see runtime.throw_geometry.impact_errors.
        telemetry_mcap_b64: the throw's 100 Hz telemetry as an MCAP file, base64-encoded.
        server_id: the server that issued the throw (its ThrowRequest's ``auth.server``), or
            None for an unnamed one: the result is that server's.
    """

    throw_id: str
    mode: Mode
    status: Literal["landed", "failed", "aborted"]
    failure_reason: str | None = None
    target_m: Vec3
    impact_m: Vec3 | None = None
    downrange_error_m: float | None = None
    crossrange_error_m: float | None = None
    policy_version: str | None = None
    policy_sha256: str | None = None
    release_stamp_s: float | None = None
    opening_stamp_s: float | None = None
    duration_s: float
    telemetry_mcap_b64: str | None = None
    server_id: str | None = None
    auth: CommandAuth | None = None


class ResultAck(Message):
    throw_id: str
    stored: bool


class LeaseRequest(Message):
    """Server -> runtime (query keys.lease): ask for this machine's lease (one writer per machine,
    runtime.service), renewing it if held; ``takeover`` takes it from another server at once (a
    deliberate, signed takeover). Must be signed; ``auth.server`` names the server."""

    machine_id: MachineId
    takeover: bool = False
    auth: CommandAuth | None = None


class LeaseAck(Message):
    """Runtime -> server: ``granted`` True when the asking server holds the lease now, for
    ``expires_in_s`` more seconds of silence; else False with the ``reason``; ``holder`` names the
    server that holds it either way (None: nobody)."""

    machine_id: MachineId
    granted: bool
    holder: str | None = None
    expires_in_s: float | None = None
    reason: str | None = None


class PolicyOffer(Message):
    """Server -> runtime: load this policy version for ``mode`` (fetch the file from
    keys.policy_file(sha256), check its SHA-256 and the manifest, swap it in between throws)."""

    machine_id: MachineId
    mode: Mode
    version: str
    sha256: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
    manifest: dict
    auth: CommandAuth | None = None


class PolicyOfferAck(Message):
    machine_id: MachineId
    accepted: bool
    reason: str | None = None


class PolicyUpdate(Stamped):
    """Runtime -> server: an offered policy version was loaded (``status`` "loaded": it runs
    from the next throw on) or could not be (``failed`` with the reason)."""

    mode: Mode
    version: str
    sha256: str
    status: Literal["loaded", "failed"]
    reason: str | None = None


M = TypeVar("M", bound=Message)


def machine_id_in(msg: Message) -> str:
    """The ``machine_id`` field of ``msg``.

    Raises:
        TypeError: ``msg``'s type has no ``machine_id`` field (it is not a per-machine message).
    """
    machine_id = getattr(msg, "machine_id", None)
    if not isinstance(machine_id, str):
        raise TypeError(f"{type(msg).__name__} has no machine_id field")
    return machine_id


def encode(msg: Message) -> bytes:
    """Serialise a message to UTF-8 JSON bytes."""
    return msg.model_dump_json().encode()


def decode(cls: type[M], payload: bytes | bytearray | memoryview | str) -> M:
    """Parse and validate a message.

    Raises:
        pydantic.ValidationError: malformed JSON, a wrong schema version, a missing or unknown
            field, a wrong vector length, or a non-finite number.
    """
    if isinstance(payload, memoryview):
        payload = payload.tobytes()
    return cls.model_validate_json(payload)


def decode_on_key(cls: type[M], key_expr: object, payload: bytes | bytearray | memoryview | str) -> M:
    """:func:`decode` a message that arrived on ``key_expr`` (a str or a ``zenoh.KeyExpr``, read
    with ``str()``) and check that it is the key's machine's (a runtime may publish only under its
    own machine id).

    Raises:
        pydantic.ValidationError: as :func:`decode`.
        ValueError: the key is not a machine/runtime key, or names another machine.
    """
    msg = decode(cls, payload)
    machine_id = machine_id_in(msg)
    if machine_id_of(str(key_expr)) != machine_id:
        raise ValueError(f"{cls.__name__} of {machine_id} on {key_expr}")
    return msg


__all__ = [name for name in dir() if name[0].isupper()] + ["encode", "decode", "decode_on_key", "machine_id_in", "ValidationError"]
