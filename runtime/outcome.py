"""What the throw executor hands back: phase events, per-tick commands, and the finished
throw's outcome (which becomes a :class:`runtime.protocol.messages.ThrowResult`)."""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass

import numpy as np

from runtime.protocol.messages import ImpactReport, ThrowResult
from runtime.telemetry import TelemetryRecorder, write_mcap


@dataclass(frozen=True)
class PhaseEvent:
    """A phase change of a throw, at machine time ``stamp_s``."""

    throw_id: str
    phase: str
    stamp_s: float
    detail: str | None = None


@dataclass
class ThrowOutcome:
    """A finished throw (what becomes a messages.ThrowResult).

    Attributes:
        status: "landed", "failed" or "aborted".
        target_m / impact_m: (3,) machine frame, m (impact None unless landed).
        downrange_error_m / crossrange_error_m: runtime.throw_geometry.impact_errors, m.
        release_stamp_s: machine time of the release command; opening_stamp_s: payload free.
        start_stamp_s / end_stamp_s: machine time of start() and of the last state seen.
        telemetry: the 100 Hz recording.
        impact: the machine's ImpactReport, if any.
    """

    throw_id: str
    mode: str
    status: str
    failure_reason: str | None
    target_m: np.ndarray
    policy_version: str
    start_stamp_s: float
    end_stamp_s: float
    telemetry: TelemetryRecorder
    impact_m: np.ndarray | None = None
    downrange_error_m: float | None = None
    crossrange_error_m: float | None = None
    release_stamp_s: float | None = None
    opening_stamp_s: float | None = None
    impact: ImpactReport | None = None
    policy_sha256: str | None = None

    @property
    def duration_s(self) -> float:
        return max(0.0, self.end_stamp_s - self.start_stamp_s)

    def to_message(self, machine_id: str, with_telemetry: bool = True) -> ThrowResult:
        """The wire ThrowResult (stamp_s = end_stamp_s), telemetry as base64 MCAP if asked."""
        mcap_b64 = None
        if with_telemetry:
            meta = {"throw_id": self.throw_id, "mode": self.mode, "status": self.status, "policy_version": self.policy_version, "target_m": json.dumps(self.target_m.tolist())}
            if self.impact_m is not None:  # the /impact point of the ROS 2 log (runtime.telemetry)
                meta["impact_m"] = json.dumps(np.asarray(self.impact_m, dtype=float).tolist())
                if self.impact is not None:
                    meta["impact_stamp_s"] = repr(float(self.impact.impact_stamp_s))
            mcap_b64 = base64.b64encode(write_mcap(self.telemetry, meta)).decode("ascii")
        return ThrowResult(
            machine_id=machine_id,
            stamp_s=self.end_stamp_s,
            throw_id=self.throw_id,
            mode=self.mode,
            status=self.status,
            failure_reason=self.failure_reason,
            target_m=self.target_m.tolist(),
            impact_m=None if self.impact_m is None else self.impact_m.tolist(),
            downrange_error_m=self.downrange_error_m,
            crossrange_error_m=self.crossrange_error_m,
            policy_version=self.policy_version,
            policy_sha256=self.policy_sha256,
            release_stamp_s=self.release_stamp_s,
            opening_stamp_s=self.opening_stamp_s,
            duration_s=self.duration_s,
            telemetry_mcap_b64=mcap_b64,
        )


@dataclass(frozen=True)
class TickOutput:
    """Commands for the machine and what happened.

    Attributes:
        valve_u: (4,) valve commands in [-1, 1] (ACTIVE_JOINTS order); zeros = neutral.
        qd_ref: (4,) references the controller tracked after safety clipping, rad/s, m/s.
        gripper_open: the gripper-open command.
        events: phase changes since the previous output.
        finished: the outcome of a throw that ended since the previous output, or None.
    """

    valve_u: np.ndarray
    qd_ref: np.ndarray
    gripper_open: bool
    events: tuple[PhaseEvent, ...] = ()
    finished: ThrowOutcome | None = None
