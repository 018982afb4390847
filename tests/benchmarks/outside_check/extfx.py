"""Effects written outside the diagnosis library for a one-off check (2026-11-22; docs/diagnosis.md, "Effects
written outside the library"): geometry errors no library effect models, a boom link longer than the MJCF says
and a gripper hanger further out along the telescope. Do not tune the diagnosis on them.

Reproduce (from this folder, 2D and 3D alike)::

    PYTHONPATH=$PWD slinger diagnose generate --mode 2d --throws 30 --real-log --profile boom.json --out /tmp/ds_boom_2d
    slinger diagnose /tmp/ds_boom_2d --workers 2
"""
from sim_twin.twin.effects import Effect, Param


class BoomLength(Effect):
    """Dipper pivot further out along the boom than the MJCF's 2.84 m: pos_x *= 1 + scale."""
    name = "boom_length"
    summary = "boom longer than modelled"
    stage = "dynamics"
    params = (Param("scale", "-", 0.0, -0.1, 0.1, "relative boom length error", "CHOSEN"),)

    def model(self, mj_model) -> None:
        b = mj_model.body("dipper").id
        mj_model.body_pos[b, 0] *= 1.0 + self.scale


class HangerLength(Effect):
    """Gripper hanger further out along the telescope than the MJCF's 2.0266 m: pos_x += extra_m."""
    name = "hanger_length"
    summary = "hanger pivot further out than modelled"
    stage = "dynamics"
    params = (Param("extra_m", "m", 0.0, -0.3, 0.3, "extra hanger offset", "CHOSEN"),)

    def model(self, mj_model) -> None:
        b = mj_model.body("gripper_hanger").id
        mj_model.body_pos[b, 0] += self.extra_m
