"""Friction of the passive gripper joints, shared by the runtime's release check, the CPU twin
and the MJX environment (array module ``xp``).

Paper eq. (1) (Sec. III-F-2):  theta_ddot_fric = upsilon * theta_dot + eta * sign(theta_dot),
identified upsilon = 0.03 1/s, eta = 0.1 rad/s^2, both passive axes alike. The paper gives it as
an acceleration opposing the motion; MuJoCo needs a generalised force, so we multiply by the
joint's effective inertia (diagonal of the mass matrix at the plumb pose, computed once per model
by :func:`runtime.dynamics.model.passive_inertia`). sign() is smoothed with tanh(v / 0.01) so that
the explicit force stays stable at 100 Hz.
"""

from __future__ import annotations

from types import ModuleType

PAPER_VISCOUS_PER_S = 0.03
PAPER_COULOMB_RAD_PER_S2 = 0.1
SIGN_SMOOTHING_RAD_PER_S = 0.01


def passive_friction_force(xp: ModuleType, qd_passive, inertia, viscous=PAPER_VISCOUS_PER_S, coulomb=PAPER_COULOMB_RAD_PER_S2):
    """Generalised friction forces on gripper_pitch and gripper_roll.

    Args:
        xp: array module.
        qd_passive: (2,) passive joint velocities, rad/s.
        inertia: (2,) effective inertias, kg m^2.
        viscous: upsilon, 1/s.  coulomb: eta, rad/s^2.

    Returns:
        (2,) forces, N m, opposing the motion.
    """
    acc = viscous * qd_passive + coulomb * xp.tanh(qd_passive / SIGN_SMOOTHING_RAD_PER_S)
    return -inertia * acc
