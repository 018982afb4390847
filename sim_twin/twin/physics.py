"""Physics shared by the CPU twin and the MJX environment: the passive joints' friction (paper
eq. (1)) and the payload's drag-free flight. Both are the runtime's (runtime.dynamics.friction,
runtime.ballistics: the release check needs them too); their names are imported here for the twin.
"""

from __future__ import annotations

from runtime.ballistics import GRAVITY_MPS2, ballistic_impact_time, ballistic_position  # noqa: F401 (re-exported)
from runtime.dynamics.friction import (  # noqa: F401 (re-exported)
    PAPER_COULOMB_RAD_PER_S2,
    PAPER_VISCOUS_PER_S,
    SIGN_SMOOTHING_RAD_PER_S,
    passive_friction_force,
)
