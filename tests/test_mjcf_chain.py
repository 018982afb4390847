"""The 3D view's machine geometry without MuJoCo (server.console.mjcf_chain): the MJCF's chain evaluated
with numpy agrees with MuJoCo's forward kinematics (here, in the test, MuJoCo may be imported) and
with the runtime's own kinematics; the API process with the 3D view on never imports MuJoCo."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import mujoco
import numpy as np
import pytest

from runtime.machine import JOINT_NAMES, forward_kinematics
from server.console.mjcf_chain import KinematicChain, default_mjcf_path, mat_to_quat, quat_to_mat
from sim_twin.twin.model import load_model
from tests.conftest import free_port


def _random_q(rng) -> np.ndarray:
    return np.concatenate([rng.uniform(-np.pi, np.pi, 1), rng.uniform([-1.34, 0.58, 0.0], [0.44, 2.78, 1.8]),
                           rng.uniform(-np.pi, np.pi, 2)])


def test_body_and_geom_poses_match_mujoco_at_random_joint_angles():
    chain, model = KinematicChain.from_mjcf(), load_model()
    data = mujoco.MjData(model)
    assert chain.joint_names == JOINT_NAMES
    assert [b.name for b in chain.bodies] == [model.body(i).name for i in range(1, model.nbody)]
    assert [g.name for g in chain.geoms] == [model.geom(i).name for i in range(model.ngeom)]
    rng = np.random.default_rng(11)
    for _ in range(50):
        q = _random_q(rng)
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        pos, rot = chain.body_poses(q)
        np.testing.assert_allclose(pos, data.xpos[1:], atol=1e-6)
        np.testing.assert_allclose(rot.reshape(-1, 9), data.xmat[1:], atol=1e-6)
        for i, (p, r) in enumerate(chain.geom_poses(q, skip_planes=False)):
            np.testing.assert_allclose(p, data.geom_xpos[i], atol=1e-6)
            np.testing.assert_allclose(r.reshape(9), data.geom_xmat[i], atol=1e-6)
    for i, g in enumerate(chain.geoms):  # the shapes' sizes and colours are MuJoCo's
        np.testing.assert_allclose(g.size, model.geom_size[i], atol=1e-9)
        assert g.rgb == tuple(int(255 * c) for c in model.geom_rgba[i][:3])


def test_chain_agrees_with_the_runtime_kinematics_and_quaternions_round_trip():
    chain = KinematicChain.from_mjcf()
    names = [b.name for b in chain.bodies]
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = _random_q(rng)
        pos, rot = chain.body_poses(q)
        pts = forward_kinematics(np, q, np.zeros(6))
        np.testing.assert_allclose(pos[names.index("boom")], pts.boom_pivot, atol=1e-9)
        np.testing.assert_allclose(pos[names.index("gripper_hanger")], pts.hanger, atol=1e-9)
        grip = pos[names.index("gripper")] + rot[names.index("gripper")] @ np.array([0.0, 0.0, -1.0])
        np.testing.assert_allclose(grip, pts.gripper_centre, atol=1e-9)
        for r in rot:
            np.testing.assert_allclose(quat_to_mat(mat_to_quat(r)), r, atol=1e-12)


def test_bad_input_is_refused_with_the_reason(tmp_path):
    chain = KinematicChain.from_mjcf(default_mjcf_path())
    with pytest.raises(ValueError, match="6 finite"):
        chain.body_poses([0.0] * 5)
    with pytest.raises(ValueError, match="6 finite"):
        chain.body_poses([0.0, np.nan, 1.0, 0.5, 0.0, 0.0])
    cases = {
        '<body><joint type="ball"/></body>': "type 'ball'",
        '<body euler="0 0 1"/>': "euler",
        '<body><geom type="mesh"/></body>': "type 'mesh'",
        '<body><geom type="box" fromto="0 0 0 1 0 0" size="1"/></body>': "fromto",
        '<body pos="1 2"/>': "needs 3 numbers",
    }
    for body, why in cases.items():
        f = tmp_path / "m.xml"
        f.write_text(f'<mujoco><compiler angle="radian"/><worldbody>{body}</worldbody></mujoco>')
        with pytest.raises(ValueError, match=why):
            KinematicChain.from_mjcf(f)
    f.write_text("<mujoco/>")
    with pytest.raises(ValueError, match="worldbody"):
        KinematicChain.from_mjcf(f)


def test_api_with_the_3d_view_on_never_imports_mujoco(tmp_path):
    code = textwrap.dedent(f"""
        import sys
        from fastapi.testclient import TestClient
        from server.app import create_app
        from server.config import Settings
        s = Settings(data_dir={str(tmp_path / 'var')!r}, viser_enabled=True, viser_port={free_port()},
                     auto_migrate=True, zenoh_listen=["tcp/127.0.0.1:{free_port()}"])
        with TestClient(create_app(s)) as c:
            assert c.get("/api/health").status_code == 200
            scene = c.app.state.scene
            assert scene is not None and scene.port
            poses = scene._geometry.poses([0.3, -0.5, 1.5, 0.9, 0.1, 0.0])
            print("GEOMS", len(poses))
        bad = sorted(m for m in sys.modules if m.split(".")[0] in ("mujoco", "sim_twin"))
        print("HEAVY", bad)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "GEOMS 7" in out.stdout and "HEAVY []" in out.stdout, out.stdout
