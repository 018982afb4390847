"""Zenoh key expressions, all composed here (zenoh-python examples: one module owns the keys).

Layout::

    slinger/machine/<machine_id>/state          MachineState     machine -> *        100 Hz pub
    slinger/machine/<machine_id>/valve_cmd      ValveCommand     runtime -> machine  100 Hz pub
    slinger/machine/<machine_id>/gripper_cmd    GripperCommand   runtime -> machine  on change (express, INTERACTIVE_HIGH)
    slinger/machine/<machine_id>/impact         ImpactReport     machine -> *        per throw
    slinger/machine/<machine_id>/sim/reset      SimReset         runtime -> sim machine only
    slinger/machine/<machine_id>/alive          liveliness token of the machine bridge / plant
    slinger/machine/<machine_id>/claim/<claim>  liveliness token of a plant claiming the machine at start
    slinger/runtime/<machine_id>/throw          queryable: ThrowRequest -> ThrowAck
    slinger/runtime/<machine_id>/abort          queryable: AbortRequest -> AbortAck
    slinger/runtime/<machine_id>/estop          AbortRequest     server -> runtime   put (the E-STOP path)
    slinger/runtime/<machine_id>/estop_ack      AbortAck         runtime -> server   per E-STOP put, after the latch is on disk (express, REAL_TIME)
    slinger/runtime/<machine_id>/info           queryable: -> RuntimeInfo
    slinger/runtime/<machine_id>/status         ThrowStatus      runtime -> server   on change
    slinger/runtime/<machine_id>/estop_reset    queryable: EstopReset -> EstopResetAck
    slinger/runtime/<machine_id>/return_to_ready queryable: ReturnToReady -> ReturnToReadyAck
    slinger/runtime/<machine_id>/runtime_state  RuntimeInfo      runtime -> *        2 Hz + on change
    slinger/runtime/<machine_id>/alive          liveliness token of the runtime
    slinger/runtime/<machine_id>/claim/<claim>  liveliness token of a runtime claiming the machine at start
    slinger/server/throw_result                 queryable on the server: ThrowResult -> ResultAck
    slinger/runtime/<machine_id>/policy/offer   queryable: PolicyOffer -> PolicyOfferAck
    slinger/runtime/<machine_id>/policy/status  PolicyUpdate     runtime -> server   on load / failure
    slinger/server/policy/<sha256>              queryable on the server: -> the ONNX file's bytes

QoS: Zenoh's defaults (priority DATA, congestion control DROP, batched) unless marked; the runtime's
publishers are declared by runtime.node.declare_publishers, the server's E-STOP puts go express on
REAL_TIME (server.fleet.estop).

Machine ids are restricted to ``[A-Za-z0-9_-]{1,64}`` so they can never inject key-expression
wildcards (``*``, ``**``, ``$*``) or separators.
"""

from __future__ import annotations

import re

ROOT = "slinger"
_MACHINE_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def validate_machine_id(machine_id: str) -> str:
    """Return ``machine_id`` unchanged if it is a legal id.

    Raises:
        ValueError: if it is empty, longer than 64 characters or contains anything but letters,
            digits, ``_`` and ``-``.
    """
    if not isinstance(machine_id, str) or not _MACHINE_ID.match(machine_id):
        raise ValueError(f"invalid machine id {machine_id!r}: use 1-64 of [A-Za-z0-9_-]")
    return machine_id


def machine(machine_id: str, leaf: str) -> str:
    """Key of the machine interface, e.g. ``machine("m1", "state")``."""
    return f"{ROOT}/machine/{validate_machine_id(machine_id)}/{leaf}"


def runtime(machine_id: str, leaf: str) -> str:
    """Key of a runtime's interface, e.g. ``runtime("m1", "throw")``."""
    return f"{ROOT}/runtime/{validate_machine_id(machine_id)}/{leaf}"


def state(machine_id: str) -> str:
    return machine(machine_id, "state")


def valve_cmd(machine_id: str) -> str:
    return machine(machine_id, "valve_cmd")


def gripper_cmd(machine_id: str) -> str:
    return machine(machine_id, "gripper_cmd")


def impact(machine_id: str) -> str:
    return machine(machine_id, "impact")


def sim_reset(machine_id: str) -> str:
    return machine(machine_id, "sim/reset")


def machine_alive(machine_id: str) -> str:
    return machine(machine_id, "alive")


def throw(machine_id: str) -> str:
    return runtime(machine_id, "throw")


def abort(machine_id: str) -> str:
    return runtime(machine_id, "abort")


def estop(machine_id: str) -> str:
    """The E-STOP put: AbortRequest, fire-and-forget (no query, no reply awaited on the sender's
    thread); the runtime confirms on :func:`estop_ack`."""
    return runtime(machine_id, "estop")


def estop_ack(machine_id: str) -> str:
    """The runtime's AbortAck of an E-STOP put (echoing its ``request_id``), published after the
    latch is written to disk."""
    return runtime(machine_id, "estop_ack")


def info(machine_id: str) -> str:
    return runtime(machine_id, "info")


def status(machine_id: str) -> str:
    return runtime(machine_id, "status")


def runtime_alive(machine_id: str) -> str:
    return runtime(machine_id, "alive")


CLAIM_RE = re.compile(r"^[0-9]{13}-[0-9a-f]{8}$")
"""A start claim: milliseconds since the epoch (13 digits) and 8 random hex digits, so that
claims sort by time, then at random (runtime.zenoh_session.claim_exclusive)."""


def _claim_leaf(claim: str) -> str:
    if claim != "*" and not CLAIM_RE.match(claim):
        raise ValueError(f"bad claim {claim!r}: expected 13 digits, '-', 8 hex digits (or '*')")
    return f"claim/{claim}"


def runtime_claim(machine_id: str, claim: str) -> str:
    """Liveliness token of a starting runtime's claim (``claim="*"``: all of the machine's claims).

    Raises:
        ValueError: a bad machine id or claim.
    """
    return runtime(machine_id, _claim_leaf(claim))


def machine_claim(machine_id: str, claim: str) -> str:
    """Liveliness token of a starting plant's claim (``claim="*"``: all of the machine's claims).

    Raises:
        ValueError: a bad machine id or claim.
    """
    return machine(machine_id, _claim_leaf(claim))


def estop_reset(machine_id: str) -> str:
    """Queryable of the runtime: signed EstopReset -> EstopResetAck."""
    return runtime(machine_id, "estop_reset")


def return_to_ready(machine_id: str) -> str:
    """Queryable of the runtime: signed ReturnToReady -> ReturnToReadyAck."""
    return runtime(machine_id, "return_to_ready")


def runtime_state(machine_id: str) -> str:
    """The runtime's RuntimeInfo, published at 2 Hz and at once on every change."""
    return runtime(machine_id, "runtime_state")


def lease(machine_id: str) -> str:
    """Queryable of the runtime: signed LeaseRequest -> LeaseAck (which server commands it)."""
    return runtime(machine_id, "lease")


def policy_offer(machine_id: str) -> str:
    return runtime(machine_id, "policy/offer")


def policy_status(machine_id: str) -> str:
    return runtime(machine_id, "policy/status")


def policy_file(sha256: str) -> str:
    """Key of a policy file the server serves; ``sha256`` must be 64 hex digits."""
    if not re.fullmatch(r"[0-9a-f]{64}", sha256 or ""):
        raise ValueError(f"invalid sha256 {sha256!r}")
    return f"{ROOT}/server/policy/{sha256}"


ALL_POLICY_STATUS = f"{ROOT}/runtime/*/policy/status"
POLICY_FILES = f"{ROOT}/server/policy/*"
ALL_STATES = f"{ROOT}/machine/*/state"
ALL_RUNTIME_ALIVE = f"{ROOT}/runtime/*/alive"
ALL_STATUS = f"{ROOT}/runtime/*/status"
ALL_RUNTIME_STATES = f"{ROOT}/runtime/*/runtime_state"
ALL_ESTOP_ACKS = f"{ROOT}/runtime/*/estop_ack"
THROW_RESULT = f"{ROOT}/server/throw_result"


def machine_id_of(key_expr: str) -> str:
    """The machine id in a key such as ``slinger/runtime/m1/alive``.

    Raises:
        ValueError: if the key is not under ``slinger/machine`` or ``slinger/runtime``.
    """
    parts = str(key_expr).split("/")
    if len(parts) < 3 or parts[0] != ROOT or parts[1] not in ("machine", "runtime"):
        raise ValueError(f"not a Slinger machine/runtime key: {key_expr!r}")
    return validate_machine_id(parts[2])
