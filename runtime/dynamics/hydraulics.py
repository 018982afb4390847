"""The hydraulic mechanism of the machine's active joints (machine-spec.md, "Hydraulic
actuation"), shared by the runtime's release check and the twin: per active joint, valve command
u in [-1, 1] -> dead band (:func:`dead_band_flow`) -> transport delay -> first-order lag
(:func:`lag_step`) -> rate-limited joint velocity (the stateful valve of the simulated machine:
sim_twin.twin.hydraulics.ValveModel), then the cylinder
(:func:`cylinder_step`): the oil displaced by that flow sets where the joint is, closed valves
hold the load (oil is incompressible: no sag or drift at neutral valves, however long), and the
cylinder's stroke ends are hard stops (no flow moves a joint past its end). The result is the
setpoint of the twin's stiff joint-velocity servo (MJCF ``<velocity>`` actuators), which alone
would let gravity sag the arm at F / kv (boom ~2 mrad/s, telescope ~4 mm/s).

Nominal parameters (sim_twin.twin.hydraulics.HydraulicParams' defaults), a HEAP-class machine:

=================  ==========  ==============================================================
parameter          nominal     source
=================  ==========  ==============================================================
transport delay    0.10 s      HEAP: response delays up to ~0.7 s (Egli & Hutter 2020/2022 via
                               machine-spec.md); hydraulic-excavator literature 0.1-0.7 s. We
                               take the low end (a well-kept machine with electro-hydraulic
                               pilot valves; the 0.7 s are HEAP's worst case) so that the
                               12.5 Hz policy can still close the loop; profiles and training
                               randomisation cover 0.05-0.25 s.
first-order lag    0.16 s      bandwidth 1/(2 pi 0.16 s) = 1.0 Hz, inside HEAP's ~0.5 Hz and
                               the literature's 0.5-2 Hz (0.5 Hz = 0.32 s, 2 Hz = 0.08 s).
dead band          0.05        proportional pilot valves with a dead band (machine-spec.md);
                               5 % of full command CHOSEN (typical 3-10 %).
rate limit         ACTIVE_     joint speed at full valve opening (runtime.machine: boom 0.45,
                   VELOCITY_   dipper 0.6 rad/s, telescope 0.75 m/s, cabin 1.0 rad/s, from the
                   LIMITS      cylinder speeds in machine-spec.md).
=================  ==========  ==============================================================
"""

from __future__ import annotations

from types import ModuleType


def dead_band_flow(xp: ModuleType, u, dead_band):
    """Normalised flow through a proportional valve with a dead band: 0 inside |u| < db, then
    linear to 1 at |u| = 1. u and dead_band broadcast; any array module."""
    return xp.sign(u) * xp.maximum(xp.abs(u) - dead_band, 0.0) / (1.0 - dead_band)


NOMINAL_DEAD_BAND = 0.05
NOMINAL_DELAY_S = 0.10
NOMINAL_LAG_S = 0.16
"""Nominal valve parameters (module docstring: sources)."""

HOLD_GAIN_PER_S = 10.0
"""Gain of the cylinder's position hold, 1/s: the servo corrects the gap between the oil-column
position and the joint at this rate (a 10 ms step closes 10 % of it; stable below 1/dt = 100).
CHOSEN: with the MJCF servo gains the static gravity sag becomes F / (kv * gain) < 0.5 mrad / mm."""


def cylinder_step(xp: ModuleType, x_ref, v_flow, q_active, lower, upper, dt_s: float, hold_gain=HOLD_GAIN_PER_S):
    """One step of the hydraulic cylinders of the active joints (any array module, broadcasts
    over leading batch axes).

    The oil the valve lets through moves the cylinder: ``x_ref`` (the joint position the oil
    column holds, rad / m) integrates the valve's joint-velocity flow and stops at the stroke
    ends. The servo setpoint follows the flow that really moved plus a hold term pulling the
    joint onto ``x_ref``, so with neutral valves the joint stays where it is (no sag) and no
    flow pushes it past an end.

    Args:
        xp: array module.
        x_ref: (..., 4) oil-column positions, rad / m (start them at the joint positions).
        v_flow: (..., 4) joint velocities the valves command, rad/s / m/s.
        q_active: (..., 4) true active joint positions.
        lower, upper: (4,) stroke ends (runtime.machine.JOINT_LOWER/UPPER[:4]; +-inf = none).
        dt_s: step, s.
        hold_gain: HOLD_GAIN_PER_S.

    Returns:
        (x_ref (..., 4) new oil-column positions, setpoint (..., 4) servo velocities).
    """
    x_new = xp.minimum(xp.maximum(x_ref + v_flow * dt_s, lower), upper)  # clip, without np.clip's wrapper
    moved = (x_new - x_ref) / dt_s
    return x_new, moved + hold_gain * (x_new - q_active)


def lag_step(y, x, lag_s, dt_s: float):
    """One backward-Euler step of the first-order lag tau * dy/dt = x - y."""
    return y + dt_s / (lag_s + dt_s) * (x - y)
