"""The MJCF model of the material handler in the twin, and the ids used everywhere.

MJCF names live here (mujoco_playground habit: one constants module, ids looked up once). The
file and its loading are the runtime's (runtime.dynamics, which the release check needs too);
their names are imported here for the twin.
"""

from __future__ import annotations

from runtime.ballistics import PAYLOAD_RADIUS_M  # noqa: F401 (re-exported; size 7 basketball, machine-spec.md)
from runtime.dynamics import MJCF_PATH  # noqa: F401 (re-exported)
from runtime.dynamics.model import fresh_model, load_model, passive_inertia, passive_inertia_of  # noqa: F401 (re-exported)

GRIPPER_CENTRE_SITE = "gripper_centre"
PAYLOAD_MASS_KG = 0.6  # not added to the model: 0.05 % of the hanging mass
