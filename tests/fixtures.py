"""Test helpers shared by several test modules."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from runtime.observation import HISTORY_STEPS, num_actions, observation_size
from runtime.policy import build_manifest, write_manifest


def write_test_policy(
    directory: Path,
    mode: str = "2d",
    name: str = "test-linear",
    seed: int = 0,
    release_after_bias: float = 0.0,
    target_range_m: tuple[float, float] = (5.0, 10.7),
    history_steps: int = HISTORY_STEPS,
) -> Path:
    """Write a small random linear-tanh ONNX policy (obs -> actions) with its manifest, reading
    ``history_steps`` control steps of joint history (runtime.observation).

    It is not a throwing policy; it exercises loading, checking and the control loop.
    The release output is ``tanh(...) + release_after_bias`` so a bias > 1.9 always releases.
    Returns the ONNX path.
    """
    rng = np.random.default_rng(seed)
    n_obs, n_act = observation_size(mode, history_steps), num_actions(mode)
    w = (rng.normal(size=(n_obs, n_act)) * 0.01).astype(np.float32)
    b = np.zeros(n_act, dtype=np.float32)
    bias = np.zeros(n_act, dtype=np.float32)
    bias[-1] = release_after_bias
    graph = helper.make_graph(
        [
            helper.make_node("MatMul", ["obs", "W"], ["h"]),
            helper.make_node("Add", ["h", "b"], ["z"]),
            helper.make_node("Tanh", ["z"], ["t"]),
            helper.make_node("Add", ["t", "bias"], ["actions"]),
        ],
        "test_policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [None, n_obs])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, [None, n_act])],
        [numpy_helper.from_array(w, "W"), numpy_helper.from_array(b, "b"), numpy_helper.from_array(bias, "bias")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8  # onnx 1.23 defaults to IR 14, which onnxruntime cannot load
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.onnx"
    onnx.save(model, path)
    write_manifest(path, build_manifest(path, mode, name, target_range_m, {"kind": "test fixture"},
                                        history_steps=history_steps))
    return path


def finished_diagnosis_run(state, machine_id: str, report: dict, profile: dict | None = None, throws: int = 30) -> str:
    """A finished ``diagnosis`` job (its row and report files) as a worker would leave it, without
    running the diagnosis; returns the run id (= job id). ``state`` is the app's ``app.state``."""
    import json

    from server.jobs.specs import job_dir

    store = state.jobs.store
    run_id = store.create("diagnosis", {"machine_id": machine_id, "limit": throws}, subject=machine_id)
    folder = job_dir(state.settings.data_dir, run_id) / "report"
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps(report))
    if profile is not None:
        (folder / "profile_fitted.json").write_text(json.dumps(profile))
    store.finish(run_id, "done", result={"throws": throws, "verdict": report.get("verdict")})
    return run_id


def raise_drift_alert(watch, machine_id: str, shift_m: float = 0.3, seed: int = 0) -> dict:
    """Raise a drift alert on ``machine_id`` through the watch's own input
    (:meth:`server.analysis.drift.DriftWatch.observe`): BASELINE_THROWS landed throws with 5 cm noise,
    then throws landing ``shift_m`` long, until the CUSUM alarms. Returns the alert.

    Raises:
        AssertionError: no alert after 100 shifted throws.
    """
    from server.analysis.drift import BASELINE_THROWS

    rng = np.random.default_rng(seed)
    for i in range(BASELINE_THROWS):
        assert watch.observe(machine_id, f"{machine_id}-base-{i}", rng.normal(0.0, 0.05, 2)) is None
    for i in range(100):
        alert = watch.observe(machine_id, f"{machine_id}-shift-{i}", rng.normal(0.0, 0.05, 2) + [shift_m, 0.0])
        if alert is not None:
            return alert
    raise AssertionError(f"no drift alert on {machine_id} after 100 throws {shift_m} m long")


def write_swing_telemetry(path: Path, seconds: float = 2.0, release_s: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Write an MCAP recording (runtime.telemetry, 100 Hz) of a made-up swing: the cabin turns
    from 0 to 0.8 rad and the boom from -0.8 to -0.5 rad (dipper 1.6 rad, telescope 0.6 m: the
    ready pose, runtime.recovery.READY_POSE), the payload released at ``release_s`` and flying on
    a parabola. It is a recording to replay, not a throw a policy made. Returns (t_s (N,), q (N, 6))."""
    from runtime.telemetry import TelemetryRecorder, write_mcap

    t = np.round(np.arange(0.0, seconds + 1e-9, 0.01), 4)
    s = t / seconds
    q = np.column_stack([0.8 * s, -0.8 + 0.3 * s, np.full_like(t, 1.6), np.full_like(t, 0.6),
                         0.2 * np.sin(3 * t), np.zeros_like(t)])
    rec = TelemetryRecorder()
    rec.event(0.0, "swinging")
    rec.event(release_s, "released")
    for i, ti in enumerate(t):
        flying = ti >= release_s
        dt = ti - release_s
        payload = [5.0 + 6.0 * dt, 0.5, 4.0 + 3.0 * dt - 4.905 * dt * dt] if flying else None
        rec.record(ti, q[i], np.zeros(6), np.zeros(4), np.zeros(4), flying, flying, "released" if flying else "swinging",
                   payload_pos_m=payload, payload_vel_mps=[6.0, 0.0, 3.0 - 9.81 * dt] if flying else None)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(write_mcap(rec))
    return t, q
