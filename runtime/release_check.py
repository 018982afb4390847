"""Release check: where the payload lands if the gripper is commanded open now.

The first release flag of the policy commands the gripper open (runtime.executor), but the payload
is free only after the gripper's opening delay (258 ms mean, 15 ms std; paper, machine-spec.md).
The gripper swings on meanwhile, so a ballistic impact from the state AT the command is off by
2.5-3.7 m on normal 2D 10 m throws (up to 10 m). :class:`ReleasePredictor` therefore

1. simulates the machine over the mean opening delay (26 physics steps of 10 ms, the twin's
   discretisation: it frees the payload on the first step at or after the delay) with MuJoCo on
   the machine's own model (runtime/dynamics/assets/material_handler.xml, loaded and checked by
   runtime.dynamics.model.load_model, as the simulated machine does). The active joints start at their
   measured velocities and move towards the joint-velocity references of the release tick (the
   controller's, after its safety clipping; the policy keeps running after the release flag)
   through the nominal valve lag
   (runtime.dynamics.hydraulics.lag_step, NOMINAL_LAG_S 0.16 s, no transport delay: the commands of the
   last 0.1 s already in the valves are much like it. CHOSEN by measurement: a 0.05-0.1 s delay
   added made it worse (30-throw probe, 2D 10 m: median 0.13 -> 0.15-0.25 m); without the
   references, joints continuing at their measured velocities, the error is up to 4 times
   larger, table below), then through the same cylinder + velocity-servo mechanism the twin
   uses (runtime.dynamics.hydraulics.cylinder_step: stroke ends are hard stops); the passive
   gripper joints swing freely with the paper's friction
   (runtime.dynamics.friction.passive_friction_force);
2. flies the gripper centre (runtime.machine.forward_kinematics) drag-free to the ground, the
   payload's centre PAYLOAD_RADIUS_M above it (runtime.ballistics, as the twin).

It knows nothing of a site's profile (masses, valve dynamics, wind, drag, grasp offset): those
are part of its error below.

Accuracy (``tests/benchmarks/release_check_accuracy.py``, ``reports/release_check_accuracy.json``, in the
lab notebook since its policies were superseded: reports/ARCHIVE.md):
100 throws per cell of the then deployed policies (throw2d-robust-e, throw3d-robust-e) on the twin by
sim_twin.evaluation.evaluate's protocol with a check that never holds, the site matrix's seeds
(``i * 100_000 + k``); horizontal distance between the executor's prediction at the release
command (measured state) and the measured impact, median / p99 / max, m:

=========================  ==================  ==================  ==================
cell                       this predictor      joints at constant  naive (state at
                                               measured velocity   the command)
=========================  ==================  ==================  ==================
2D 7.5 m nominal           0.05 / 0.16 / 0.19  0.14 / 0.54 / 0.60  0.46 / 1.16 / 1.51
2D 10 m nominal            0.11 / 0.55 / 0.61  0.47 / 1.96 / 2.21  2.46 / 3.54 / 3.69
3D 7 m nominal             0.09 / 0.26 / 0.28  0.15 / 0.56 / 0.57  0.61 / 0.97 / 1.08
3D 9.5 m nominal           0.12 / 0.38 / 0.40  0.40 / 1.25 / 1.35  1.82 / 2.43 / 2.43
2D 7.5 m slow_hydraulics   0.11 / 0.35 / 0.37  0.08 / 0.35 / 0.44  0.49 / 1.14 / 1.17
2D 10 m slow_hydraulics    0.21 / 0.76 / 0.92  0.48 / 1.59 / 1.75  2.24 / 2.90 / 3.18
3D 7 m slow_hydraulics     0.14 / 0.53 / 0.55  0.18 / 0.82 / 0.89  0.66 / 0.98 / 1.11
3D 9.5 m slow_hydraulics   0.52 / 2.33 / 3.09  0.45 / 2.26 / 4.90  2.28 / 4.40 / 4.79
=========================  ==================  ==================  ==================

The last cell holds the slow valves' (0.2 s delay, 0.3 s lag, not modelled) largest errors and two
wild releases (10.0 and 5.4 m from the target, predicted 11.5 and 6.3 m); the largest PREDICTED
distance from the target of a throw that landed within 3 m was 1.2 m there, <= 0.9 m elsewhere.

Cost: 0.5-0.9 ms per prediction (median per cell; max 1-5 ms, one 30 ms outlier on the loaded
2-core development host; one MjData per thread, reused, the model loaded once per process); it runs only on a
release flag, at most once per 80 ms control step.

Availability: the model and the dynamics are the runtime's own (runtime.dynamics); MuJoCo is the
runtime wheel's ``release-check`` extra. :meth:`ReleaseCheck.load` gives the reason when MuJoCo or
the model cannot be loaded; the runtime says so at start-up (runtime.node) and the executor then
refuses every throw with that reason (runtime.executor: fail closed) unless the check is switched
off explicitly. Whoever builds an executor hands it its :class:`ReleaseCheck` (one per thread:
the predictor's MjData is scratch space that MuJoCo does not guard); the radius is the
executor's configuration (runtime.executor.ExecutorConfig), given by the runtime's
``--release-check-radius`` and, for previews, by the server's settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from runtime.ballistics import ground_impact
from runtime.machine import JOINT_LOWER, JOINT_UPPER, NUM_ACTIVE, NUM_JOINTS, forward_kinematics

OPENING_DELAY_MEAN_S = 0.258
"""Mean opening delay of the gripper, s (paper; shared/reference/machine-spec.md; std 15 ms)."""
DEFAULT_RADIUS_M = 3.0
"""runtime.executor.ExecutorConfig.release_check_radius_m's default (its docstring: why)."""


def parse_radius(text) -> float | None:
    """A radius > 0 in m (number or text), or "off" / None -> None (check off).

    Raises:
        ValueError: anything else (negative, zero, infinite, NaN, not a number).
    """
    if text is None or str(text).strip().lower() == "off":
        return None
    try:
        r = float(text)
    except ValueError:
        r = math.nan
    if not (r > 0 and math.isfinite(r)):
        raise ValueError(f"release check radius must be a number of metres > 0 or 'off', got {text!r}")
    return r


class ReleasePredictor:
    """Predicts the payload's impact point for a release commanded at a measured state.

    Args:
        model: a mujoco.MjModel of the machine (runtime.dynamics.model.load_model's checks:
            joints in JOINT_NAMES order, actuators = the 4 active joints as velocity servos).
        opening_delay_s: gripper opening delay to simulate, s (default the paper's mean).

    Raises:
        ImportError: MuJoCo is not installed (the runtime wheel's ``release-check`` extra).
    """

    def __init__(self, model, opening_delay_s: float = OPENING_DELAY_MEAN_S):
        import mujoco

        from runtime.dynamics.friction import passive_friction_force
        from runtime.dynamics.hydraulics import NOMINAL_LAG_S, cylinder_step, lag_step
        from runtime.dynamics.model import passive_inertia_of

        self._mj, self._cylinder_step, self._friction = mujoco, cylinder_step, passive_friction_force
        self._lag_step, self.lag_s = lag_step, NOMINAL_LAG_S
        self.model = model
        self.data = mujoco.MjData(model)
        self.dt_s = float(model.opt.timestep)
        self.steps = int(math.ceil(opening_delay_s / self.dt_s - 1e-9))
        self._inertia = passive_inertia_of(model)
        self._lo, self._hi = JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE]

    def predict(self, q, qd, qd_ref=None) -> np.ndarray:
        """Impact point of a release commanded now.

        Args:
            q: (6,) measured joint positions, JOINT_NAMES order (rad, telescope m).
            qd: (6,) measured joint velocities (rad/s, telescope m/s).
            qd_ref: (4,) joint-velocity references of the active joints commanded with the
                release (rad/s, m/s; the executor passes runtime.controller's reference after
                safety clipping), or None: the active joints keep their measured velocities.

        Returns:
            (3,) impact point of the payload's centre on the ground, machine frame, m (z = 0).

        Raises:
            ValueError: q, qd or qd_ref misshaped or non-finite, or the simulation diverged.
        """
        q, qd = np.asarray(q, dtype=float), np.asarray(qd, dtype=float)
        ref = qd[:NUM_ACTIVE] if qd_ref is None else np.asarray(qd_ref, dtype=float)
        if q.shape != (NUM_JOINTS,) or qd.shape != (NUM_JOINTS,) or ref.shape != (NUM_ACTIVE,):
            raise ValueError(f"q, qd must have shape ({NUM_JOINTS},), qd_ref ({NUM_ACTIVE},); got {q.shape}, {qd.shape}, {ref.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd)) and np.all(np.isfinite(ref))):
            raise ValueError("non-finite joint state or reference")
        mj, d = self._mj, self.data
        mj.mj_resetData(self.model, d)
        d.qpos[:], d.qvel[:] = q, qd
        x_ref, v_flow = np.clip(q[:NUM_ACTIVE], self._lo, self._hi), qd[:NUM_ACTIVE]
        for _ in range(self.steps):
            v_flow = self._lag_step(v_flow, ref, self.lag_s, self.dt_s)
            x_ref, d.ctrl[:] = self._cylinder_step(np, x_ref, v_flow, d.qpos[:NUM_ACTIVE], self._lo, self._hi, self.dt_s)
            d.qfrc_applied[4:6] = self._friction(np, d.qvel[4:6], self._inertia)
            mj.mj_step(self.model, d)
        pts = forward_kinematics(np, d.qpos.copy(), d.qvel.copy())
        p0, v0 = np.asarray(pts.gripper_centre, dtype=float), np.asarray(pts.gripper_centre_vel, dtype=float)
        hit, _ = ground_impact(p0, v0)
        if not np.all(np.isfinite(hit)):
            raise ValueError("impact prediction diverged")
        return hit


@lru_cache(maxsize=1)
def _machine_model():
    """The machine's MjModel, loaded once per process (read-only once loaded)."""
    from runtime.dynamics.model import load_model

    return load_model()


@dataclass(frozen=True)
class ReleaseCheck:
    """What an executor checks release flags with: a predictor, or why there is none.

    Attributes:
        predictor: the predictor, or None when it cannot be built.
        unavailable: why there is no predictor (the executor refuses throws with it), else None.
    """

    predictor: ReleasePredictor | None
    unavailable: str | None = None

    @classmethod
    def load(cls) -> ReleaseCheck:
        """A check on the machine's MJCF (runtime.dynamics), or the reason it cannot be built
        (MuJoCo missing: ImportError; the MJCF unreadable or in another joint order: OSError,
        ValueError of runtime.dynamics.model.load_model). Each call makes a new predictor (its
        own MjData); the model is loaded once per process."""
        try:
            return cls(ReleasePredictor(_machine_model()))
        except (ImportError, OSError, ValueError) as e:
            return cls(None, f"{type(e).__name__}: {e}")
