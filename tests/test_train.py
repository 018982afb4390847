"""PPO training on the CPU with tiny settings: checkpoints, exact resume, curve, ONNX export."""

from __future__ import annotations

import argparse

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("jax")
pytestmark = pytest.mark.torch

from runtime.policy import PolicyRunner  # noqa: E402
from sim_twin import train  # noqa: E402


def _args(tmp_path, **kw):
    p = argparse.ArgumentParser()
    train.build_parser(p)
    argv = ["--mode", "2d", "--num-envs", "8", "--iterations", "2", "--chunk", "1", "--log-dir", str(tmp_path / "run")]
    for k, v in kw.items():
        argv += [f"--{k.replace('_', '-')}", str(v)]
    return p.parse_args(argv)


def test_train_checkpoint_resume_export(tmp_path):
    assert train.run(_args(tmp_path)) == 0
    ckpt = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=False)
    assert {"actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter"} <= set(state)
    first_iter = state["iter"]

    onnx = tmp_path / "p.onnx"
    assert train.run(_args(tmp_path, iterations=1, resume=ckpt, export=onnx, name="tiny")) == 0
    resumed = torch.load(ckpt, weights_only=False)
    assert resumed["iter"] > first_iter  # continued, not restarted
    rows = (tmp_path / "run" / "curve.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 3  # header + 2 chunks + 1 resumed chunk
    assert (tmp_path / "run" / "training_curve.png").stat().st_size > 1000
    runner = PolicyRunner.load(onnx)
    assert runner.version == "tiny" and runner.mode == "2d"
