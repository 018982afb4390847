"""The diagnosis reads rosbag2: bags written by rosbags' own Writer (MCAP and sqlite3 storage),
mapped with the ROS 2 bridge's file (degrees, millimetres, per-cent valves, an IMU for the passive
joints), converted by `slinger diagnose convert` and diagnosed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from scipy.spatial.transform import Rotation

from runtime.ros2 import types as rt
from runtime.ros2.imu import imu_from_joints
from runtime.ros2.robot_description import UrdfChain
from sim_twin.diagnosis import dataset, rosbag
from sim_twin.diagnosis.cli import main as diagnose_main
from sim_twin.diagnosis.convert import ConvertError
from sim_twin.twin.profile import SensorParams

POLICY = Path(__file__).parent.parent / "policies" / "throw2d.onnx"
IDEAL = {k: 0.0 for k in SensorParams.__dataclass_fields__}
JAZZY = get_typestore(Stores.ROS2_JAZZY)
DEG = np.pi / 180
YAW = Rotation.from_euler("z", 0.7)

MAPPING = {
    "machine_id": "rosbag-site", "mode": "2d",
    "topics": {"joint_states": "/arm/joint_states", "gripper_state": "/gripper/state", "valve_command": "/arm/valve_commands",
               "gripper_command": "/gripper/command", "imu": "/gripper/imu"},
    "joints": {"boom": {"name": "boom_joint", "scale": DEG}, "dipper": {"name": "stick_joint", "scale": DEG},
               "telescope": {"name": "telescope_joint", "scale": 0.001}},
    "valves": {j: {"index": i, "scale": 100.0} for i, j in enumerate(["telescope", "dipper", "boom", "cabin_turn"])},
    "sensors": {"impact_sigma_m": 0.05},
}


@pytest.fixture(scope="module")
def nominal(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("nominal")
    dataset.generate(d, {"name": "nominal", "sensing": IDEAL}, 6, POLICY, seed=11, workers=1)
    return d


def write_bag(path: Path, th: dataset.LoggedThrow, storage: StoragePlugin) -> None:
    """One logged throw as a ROS 2 machine would record it (rosbags' Writer, receive times = stamps)."""
    chain = UrdfChain()
    t0_ns = 1_700_000_000_000_000_000
    with Writer(path, version=9, storage_plugin=storage) as w:
        conns = {topic: w.add_connection(topic, typename, typestore=JAZZY) for topic, typename in (
            ("/arm/joint_states", rt.JOINT_STATE), ("/gripper/imu", rt.IMU), ("/arm/valve_commands", rt.FLOAT64_MULTI_ARRAY),
            ("/gripper/command", rt.BOOL), ("/gripper/state", rt.BOOL), ("/unrelated", rt.STRING))}

        def put(topic, t_ns, msg):
            w.write(conns[topic], t_ns, JAZZY.serialize_cdr(msg, msg.__msgtype__))

        for i, t in enumerate(th.t_s):
            ns = t0_ns + round(t * 1e9)
            q, qd = th.q[i], th.qd[i]
            put("/arm/joint_states", ns, rt.joint_state(ns * 1e-9, ["cabin_turn", "boom_joint", "stick_joint", "telescope_joint"],
                                                         [q[0], q[1] / DEG, q[2] / DEG, q[3] * 1000], [qd[0], qd[1] / DEG, qd[2] / DEG, qd[3] * 1000]))
            _p, quat = chain.link_pose("gripper", dict(zip(["cabin_turn", "boom", "dipper", "telescope", "gripper_pitch", "gripper_roll"], q)))
            _q, omega = imu_from_joints(q, qd)  # the angular velocity in the IMU's frame
            quat = (YAW * Rotation.from_quat(quat)).as_quat()  # an AHRS whose north is not the cabin's x axis
            imu = rt.msg(rt.IMU, header=rt.header(ns * 1e-9, "gripper"), orientation=rt.quaternion(quat), orientation_covariance=np.zeros(9),
                         angular_velocity=rt.vector3(omega), angular_velocity_covariance=np.zeros(9),
                         linear_acceleration=rt.vector3((0, 0, 9.81)), linear_acceleration_covariance=np.zeros(9))
            put("/gripper/imu", ns - 1000, imu)  # received just before the joint states (newest earlier is matched)
            u = th.valve_u[i]
            put("/arm/valve_commands", ns, rt.float64_array([u[3] * 100, u[2] * 100, u[1] * 100, u[0] * 100]))
            put("/gripper/command", ns, rt.msg(rt.BOOL, data=bool(i >= th.cmd_row)))
            put("/gripper/state", ns, rt.msg(rt.BOOL, data=bool(th.open_row is not None and i >= th.open_row)))
            if i % 50 == 0:
                put("/unrelated", ns, rt.msg(rt.STRING, data="ignored"))


def test_rosbag2_of_another_library_converts_and_diagnoses(nominal: Path, tmp_path: Path):
    throws, _ = dataset.load(nominal)
    bags = []
    for k, th in enumerate(throws):
        storage = StoragePlugin.MCAP if k % 2 == 0 else StoragePlugin.SQLITE3
        write_bag(tmp_path / "bags" / th.throw_id, th, storage)
        bags.append(tmp_path / "bags" / th.throw_id)
    assert (bags[1] / f"{th.throw_id}.db3").exists() or any(bags[1].glob("*.db3"))
    assert all(rosbag.is_rosbag(b) for b in bags) and not rosbag.is_rosbag(nominal / "index.json")
    mapping = tmp_path / "site.json"
    mapping.write_text(json.dumps(MAPPING))
    lines = ["throw_id,target_x_m,target_y_m,impact_x_m,impact_y_m"] + [
        f"{th.throw_id},{th.target_m[0]},{th.target_m[1]},{th.impact_m[0]},{th.impact_m[1]}" for th in throws]
    (tmp_path / "impacts.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "ds"
    assert diagnose_main(["convert", *map(str, bags), "--mapping", str(mapping), "--impacts", str(tmp_path / "impacts.csv"),
                          "--out", str(out)]) == 0
    got, got_index = dataset.load(out)
    assert got_index["machine_id"] == "rosbag-site" and got_index["sensors"] == {"impact_sigma_m": 0.05}
    assert [g.throw_id for g in got] == [th.throw_id for th in throws]
    for g, th in zip(got, throws):
        n = len(th.t_s)
        assert g.cmd_row == th.cmd_row and g.open_row == th.open_row
        np.testing.assert_allclose(g.q[-n:, :4], th.q[:, :4], atol=1e-9)
        np.testing.assert_allclose(g.q[-n:, 4:], th.q[:, 4:], atol=1e-9)  # passive angles back from the IMU orientation
        np.testing.assert_allclose(g.qd[-n:], th.qd, atol=1e-9)  # rates: the JointState's and the IMU's angular velocity
        np.testing.assert_allclose(g.valve_u[-n:], th.valve_u, atol=1e-12)
        np.testing.assert_allclose(g.impact_m, th.impact_m)
    assert diagnose_main([str(out), "--out", str(tmp_path / "report"), "--no-plots", "--workers", "1"]) == 0
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["verdict"]["answer"] in ("no_gap", "unexplained", "named", "ambiguous")


def test_bad_bags_and_mappings_are_clear_errors(nominal: Path, tmp_path: Path):
    (th, *_), _ = dataset.load(nominal)
    write_bag(tmp_path / "t1", th, StoragePlugin.MCAP)
    good = rosbag.BagMapping.model_validate(MAPPING)
    with pytest.raises(ConvertError, match="no messages on /elsewhere"):
        rosbag.convert_bag(tmp_path / "t1", good.model_copy(update={"topics": good.topics.model_copy(update={"joint_states": "/elsewhere"})}))
    with pytest.raises(ConvertError, match="type std_msgs/msg/String, expected sensor_msgs/msg/JointState"):
        rosbag.convert_bag(tmp_path / "t1", good.model_copy(update={"topics": good.topics.model_copy(update={"joint_states": "/unrelated"})}))
    with pytest.raises(ConvertError, match="named for both"):
        rosbag.convert_bag(tmp_path / "t1", good.model_copy(update={"topics": good.topics.model_copy(update={"joint_states": "/gripper/state"})}))
    with pytest.raises(ConvertError, match="lacks one of"):
        rosbag.convert_bag(tmp_path / "t1", good.model_copy(update={"joints": {"boom": good.joint("boom").model_copy(update={"name": "nope"})}}))
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 99}\n")
    with pytest.raises(ConvertError, match="not a readable rosbag2"):
        rosbag.convert_bag(tmp_path / "junk", good)
    (tmp_path / "m.toml").write_text("mode = '4d'\n")
    with pytest.raises(ConvertError, match="mode"):
        rosbag.load_mapping(tmp_path / "m.toml")
    (tmp_path / "impacts.csv").write_text("throw_id,target_x_m,target_y_m,impact_x_m,impact_y_m\nother,8,0,8,0\n")
    (tmp_path / "site.json").write_text(json.dumps(MAPPING))
    with pytest.raises(ConvertError, match="has no row"):
        rosbag.convert([tmp_path / "t1"], tmp_path / "site.json", tmp_path / "impacts.csv", tmp_path / "ds")
    assert not (tmp_path / "ds").exists()


def _zip_dir(d: Path) -> bytes:
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(d.iterdir()):
            zf.write(p, f"{d.name}/{p.name}")
    return buf.getvalue()


def test_bags_uploaded_through_the_api_are_diagnosed(client, nominal: Path, tmp_path: Path):
    """POST /api/diagnosis/uploads: single MCAP files and zipped rosbag2 directories (sqlite3),
    the mapping and the impacts CSV; converted and diagnosed by the worker."""
    from server.analysis.diagnosis import DiagnosisRuns

    runs = DiagnosisRuns(client.app.state.sessions, client.app.state.jobs, client.app.state.settings.data_dir, workers=1)
    client.app.state.diagnosis_runs = runs
    throws, _ = dataset.load(nominal)
    files = []
    for k, th in enumerate(throws):
        d = tmp_path / "bags" / th.throw_id
        write_bag(d, th, StoragePlugin.MCAP if k % 2 == 0 else StoragePlugin.SQLITE3)
        if k % 2 == 0:
            (mcap,) = d.glob("*.mcap")
            files.append(("bags", (f"{th.throw_id}.mcap", mcap.read_bytes(), "application/octet-stream")))
        else:
            files.append(("bags", (f"{th.throw_id}.zip", _zip_dir(d), "application/zip")))
    impacts = "throw_id,target_x_m,target_y_m,impact_x_m,impact_y_m\n" + "".join(
        f"{th.throw_id},{th.target_m[0]},{th.target_m[1]},{th.impact_m[0]},{th.impact_m[1]}\n" for th in throws)
    mapping = ("mapping", ("site.json", json.dumps(MAPPING).encode(), "application/json"))

    def post(bag_files, impacts_text=impacts, mapping_part=mapping):
        return client.post("/api/diagnosis/uploads", data={"machine_id": "ros-site"},
                           files=[*bag_files, mapping_part, ("impacts", ("impacts.csv", impacts_text.encode(), "text/csv"))])

    # refused before any work, with the reason; nothing is kept
    assert "no row for throws" in post(files, impacts.splitlines()[0] + "\n" + "".join(impacts.splitlines(True)[2:])).json()["detail"]
    assert "a bag is a" in post([("bags", ("t.txt", b"x", "text/plain"))]).json()["detail"]
    assert "not a zip" in post([("bags", (f"{throws[1].throw_id}.zip", b"PK-not", "application/zip"))]).json()["detail"]
    assert post(files, mapping_part=("mapping", ("site.ini", b"", "text/plain"))).status_code == 422
    assert "two bags" in post(files + files[:1]).json()["detail"]
    assert runs.list() == []
    client.cookies.clear()
    assert post(files).status_code == 401
    from tests.conftest import ADMIN, login

    login(client, *ADMIN)
    r = post(files)
    assert r.status_code == 202, r.text
    run_id = r.json()["id"]
    runs.wait(600)
    st = client.get(f"/api/diagnosis/runs/{run_id}").json()
    assert st["status"] == "done", st.get("error")
    assert st["source"] == "rosbag2 upload" and st["machine_id"] == "ros-site" and st["report"]["throws"] == len(throws)
