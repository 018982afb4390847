"""The machine's dynamics that the runtime and the twin share (the bottom of the stack: imports
nothing of sim_twin or server).

* :data:`MJCF_PATH`: the machine's MuJoCo model (``assets/material_handler.xml``), loaded and
  checked by :mod:`runtime.dynamics.model` (needs MuJoCo: the runtime wheel's ``release-check``
  extra; this package itself imports no MuJoCo, so the light runtime and the server can find
  the file without it).
* :mod:`runtime.dynamics.hydraulics`: the valve dead band, the valve lag step and the hydraulic
  cylinder step (numpy or any array module).
* :mod:`runtime.dynamics.friction`: the passive joints' friction (paper eq. (1)).
* The drag-free flight of the payload is :mod:`runtime.ballistics`.

The release check (runtime.release_check) simulates the machine with these; the twin
(sim_twin.twin.model, sim_twin.twin.hydraulics, sim_twin.twin.physics, sim_twin.training.mjx_env) builds on them.
"""

from pathlib import Path

MJCF_PATH = Path(__file__).parent / "assets" / "material_handler.xml"
"""The machine's MJCF: joints in runtime.machine.JOINT_NAMES order, the four active joints'
velocity servos as actuators."""
