"""tests/benchmarks/checkpoint_average.py: the mean of a run's gate candidates is a policy the runtime
loads, the mean of one network with itself is that network, and candidates of other networks are refused."""

import json
import shutil
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from runtime.policy import PolicyRunner
from tests.benchmarks.checkpoint_average import main

ROOT = Path(__file__).resolve().parents[1]
H0 = ROOT / "policies" / "training" / "throw2d-scratch-h0"


def _act(path: Path, obs: np.ndarray) -> np.ndarray:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"obs": obs})[0]


def test_mean_of_two_candidates_loads_and_lies_between_them(tmp_path):
    a, b = H0 / "candidates" / "checkpoint_500.onnx", H0 / "throw2d.onnx"
    out = tmp_path / "avg.onnx"
    assert main([str(out), str(a), str(b), "--name", "throw2d-avg"]) == 0
    policy = PolicyRunner.load(out)  # checks the manifest's SHA-256 against the file
    manifest = json.loads(out.with_suffix(".json").read_text())
    assert policy.version == "throw2d-avg" and "model_card" not in manifest["training"]
    assert manifest["training"]["averaged_from"] == [str(a), str(b)]
    obs = np.zeros((1, manifest["observation_size"]), np.float32)
    assert not np.allclose(_act(out, obs), _act(a, obs)) and not np.allclose(_act(out, obs), _act(b, obs))


def test_the_mean_of_a_network_with_itself_is_that_network(tmp_path):
    a = tmp_path / "a.onnx"
    shutil.copy(H0 / "throw2d.onnx", a)
    shutil.copy(H0 / "throw2d.json", a.with_suffix(".json"))
    assert main([str(tmp_path / "avg.onnx"), str(a), str(a)]) == 0
    size = json.loads(a.with_suffix(".json").read_text())["observation_size"]
    obs = np.random.default_rng(0).normal(size=(4, size)).astype(np.float32)
    np.testing.assert_allclose(_act(tmp_path / "avg.onnx", obs), _act(a, obs), rtol=1e-6, atol=1e-6)


def test_other_networks_and_a_single_candidate_are_refused(tmp_path, capsys):
    out = tmp_path / "avg.onnx"
    assert main([str(out), str(H0 / "throw2d.onnx"), str(ROOT / "policies" / "throw3d.onnx")]) == 2
    assert "differ" in capsys.readouterr().err and not out.exists()
    assert main([str(out), str(H0 / "throw2d.onnx")]) == 2
    assert "at least two" in capsys.readouterr().err
