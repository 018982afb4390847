"""Server-side gating of throws: a throw needs a fresh OK preview of the same request.

The console greys out its Throw button until a preview is OK, but the server must not trust the
browser: :func:`preview_refusal` checks the preview a throw names against the throw request, the
machine's current state and the policy its runtime runs now. Each failed condition has a name
(returned to API clients in the ``X-Refused-Condition`` header) and a message that says what to do.

Conditions, in the order checked (status code):

=================  ====  ==========================================================================
``preview_missing``  422  no ``preview_id`` given
``preview_unknown``  422  the id is unknown or was evicted (the server keeps the last 200)
``preview_failed``   422  the preview's twin swing failed (its reason)
``preview_other``    422  made for another machine or mode
``preview_target``   422  made for a target further than ``target_tolerance_m`` from this one
``keep_out_scatter`` 422  the preview's ``scatter_sigmas`` ellipse (or, without one, its nominal
                          impact plus ``nominal_margin_m``) reaches a keep-out zone
                          (server.throws.targets.scatter_refusal)
``preview_stale``    409  older than ``max_age_s``
``policy_changed``   409  the runtime's policy for the mode (SHA-256) is not the previewed one
``machine_moved``    409  an active joint moved more than ``max_active_joint_delta`` (rad or m,
                          telescope) or a passive joint more than ``max_passive_joint_delta`` rad
                          since the preview's start state
=================  ====  ==========================================================================
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

from runtime.machine import JOINT_NAMES
from server.errors import Conflict, DomainError, Refused
from server.throws.targets import scatter_refusal

if TYPE_CHECKING:
    from server.config import Settings


@dataclass(frozen=True)
class GateLimits:
    """Bounds of the preview gate (server.config.Settings holds the deployed values).

    Attributes:
        max_age_s: a preview older than this is stale, s. 60 s: time to look at the preview
            and confirm, short enough that the site has not changed (CHOSEN).
        target_tolerance_m: the throw's target may differ from the previewed one by this much
            (Euclidean, m); 0.05 m is half the 2D accuracy bar's sigma (CHOSEN).
        max_active_joint_delta: largest change of an active joint (cabin_turn, boom, dipper in
            rad; telescope in m) since the preview's start state. 0.05 rad moves the gripper of the
            ~9 m arm by ~0.45 m, the scale at which the predicted impact shifts visibly (CHOSEN).
        max_passive_joint_delta: same for the passive gripper joints, rad; larger, because the
            hanging gripper keeps swaying a little after the machine stops (CHOSEN).
        scatter_sigmas: the preview's Monte Carlo ellipse, scaled to this many sigma, must stay
            out of every keep-out zone; 3 sigma holds 98.9 % of a 2-D Gaussian's impacts (CHOSEN).
        nominal_margin_m: without an ellipse (a nominal-only preview) the predicted impact must
            lie this far outside every zone, m; 3 x the 3D site-matrix sigma bar of 0.20 m
            (CHOSEN; docs/training.md).
    """

    max_age_s: float = 60.0
    target_tolerance_m: float = 0.05
    max_active_joint_delta: float = 0.05
    max_passive_joint_delta: float = 0.3
    scatter_sigmas: float = 3.0
    nominal_margin_m: float = 0.6

    @classmethod
    def from_settings(cls, settings: Settings) -> GateLimits | None:
        """The preview gate's bounds from the server's settings, or None when ``require_preview`` is off."""
        if not settings.require_preview:
            return None
        return cls(settings.preview_max_age_s, settings.preview_target_tolerance_m,
                   settings.preview_max_active_joint_delta, settings.preview_max_passive_joint_delta,
                   settings.keep_out_scatter_sigmas, settings.keep_out_margin_m)


@dataclass(frozen=True)
class Refusal:
    """A failed gate condition: ``error`` is the domain error to raise (server.errors.Refused for
    a preview that does not match the request, Conflict for one the state has outrun)."""

    error: type[DomainError]
    condition: str
    message: str


def preview_refusal(preview: dict | None, preview_id: str | None, machine_id: str, mode: str,
                    target_m: list[float], current_q: list[float], policy_sha256: str | None,
                    now: datetime, limits: GateLimits, zones: Sequence = ()) -> Refusal | None:
    """Why the preview does not allow this throw now, or None if it does.

    Args:
        preview: the stored preview summary (server.throws.previews: ``status``, ``reason``,
            ``machine_id``, ``mode``, ``target_m``, ``created_at`` ISO 8601 with zone,
            ``start_q`` (6,), ``policy_sha256``), or None if ``preview_id`` is unknown.
        target_m: (3,) the throw's target, machine frame, m.
        current_q: (6,) the machine's current joint positions (JOINT_NAMES order).
        policy_sha256: SHA-256 of the policy the runtime runs for ``mode`` now (None: unknown).
        now: UTC-aware current time.
        zones: the site's keep-out zones (server.config.KeepOutZone).
    """
    again = "preview again"
    if preview_id is None:
        return Refusal(Refused, "preview_missing", "a throw needs an OK preview of the same request: send its preview_id")
    if preview is None:
        return Refusal(Refused, "preview_unknown", f"unknown or expired preview {preview_id!r}: {again}")
    if preview.get("status") != "ok":
        return Refusal(Refused, "preview_failed", f"the preview failed ({preview.get('reason') or 'no reason'}): "
                                              "this throw would fail too")
    if preview["machine_id"] != machine_id or preview["mode"] != mode:
        return Refusal(Refused, "preview_other", f"the preview was made for another machine or mode "
                                             f"({preview['machine_id']} {preview['mode']}): {again}")
    off_m = math.dist(preview["target_m"], target_m)
    if off_m > limits.target_tolerance_m:
        return Refusal(Refused, "preview_target", f"the preview was made for another target ({off_m:.2f} m away, "
                                              f"tolerance {limits.target_tolerance_m:.2f} m): {again}")
    scatter = scatter_refusal(preview, zones, limits.scatter_sigmas, limits.nominal_margin_m)
    if scatter is not None:
        return Refusal(Refused, "keep_out_scatter", scatter)
    age_s = (now - datetime.fromisoformat(preview["created_at"])).total_seconds()
    if age_s > limits.max_age_s:
        return Refusal(Conflict, "preview_stale", f"the preview is {age_s:.0f} s old (at most {limits.max_age_s:.0f} s): {again}")
    if policy_sha256 is None or preview.get("policy_sha256") != policy_sha256:
        return Refusal(Conflict, "policy_changed", f"the machine's {mode} policy changed since the preview: {again}")
    for i, name in enumerate(JOINT_NAMES):
        bound = limits.max_active_joint_delta if i < 4 else limits.max_passive_joint_delta
        delta = abs(current_q[i] - preview["start_q"][i])
        if delta > bound:
            unit = "m" if name == "telescope" else "rad"
            return Refusal(Conflict, "machine_moved", f"the machine moved since the preview ({name.replace('_', ' ')} by "
                                                      f"{delta:.3f} {unit}, at most {bound:.3f} {unit}): {again}")
    return None
