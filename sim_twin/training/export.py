"""Export a trained checkpoint to ONNX with its manifest (the policy-version format of
runtime.policy).

The graph is rsl_rl's ONNX wrapper of the actor (``obs`` -> ``actions``, the empirical
observation normaliser baked in, deterministic mean action). onnx >= 1.23 writes IR 14 by default,
which onnxruntime cannot load, so the opset is pinned to 17 and the IR version to 8.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path

import numpy as np

from runtime.observation import HISTORY_STEPS, num_actions, observation_size
from runtime.policy import PolicyRunner, build_manifest, write_manifest

log = logging.getLogger(__name__)

ONNX_OPSET = 17
ONNX_IR_VERSION = 8


def history_steps(cfg: dict) -> int:
    """Control steps of joint history the config's actor reads (``env.history_steps``, else the
    default runtime.observation.HISTORY_STEPS: configs written before the option have none)."""
    return int(cfg["env"].get("history_steps", HISTORY_STEPS))


def load_actor(checkpoint: Path, cfg: dict, cls=None):
    """The actor of an rsl_rl checkpoint as ``cls`` (default rsl_rl's MLPModel; a subclass such as
    sim_twin.training.models.Float32MLPModel takes the same state), built from ``cfg``'s
    ``runner.actor`` for its mode's and history's observation and action sizes (runtime.observation), its std
    parameter converted where the checkpoint's parameterisation differs
    (critic_surgery.match_std_parameter), in eval mode.

    Returns:
        (actor, the loaded checkpoint dict: ``iter``, ``actor_state_dict``, ...).
    """
    import torch
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    from sim_twin.training.critic_surgery import match_std_parameter

    mode = cfg["env"]["mode"]
    obs = TensorDict({"policy": torch.zeros(1, observation_size(mode, history_steps(cfg)))}, batch_size=[1])
    actor_cfg = copy.deepcopy(cfg["runner"]["actor"])
    actor_cfg.pop("class_name")
    actor = (cls or MLPModel)(obs, {"actor": ["policy"]}, "actor", num_actions(mode), **actor_cfg)
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    actor.load_state_dict(match_std_parameter(state["actor_state_dict"], cfg["runner"]["actor"])[0])
    return actor.eval(), state


def export_checkpoint(checkpoint: Path, cfg: dict, out_path: Path, name: str) -> Path:
    """Write ``out_path`` (.onnx) and its ``.json`` manifest from an rsl_rl checkpoint.

    Args:
        checkpoint: checkpoint.pt written by sim_twin.training.train.
        cfg: the training config (env + runner + num_envs) it was trained with.
        out_path: ONNX file to write.
        name: policy version name.

    Returns:
        out_path. Raises runtime.policy.PolicyError if the result does not load in the runtime.
    """
    import onnx
    import torch

    mode = cfg["env"]["mode"]
    n_obs = observation_size(mode, history_steps(cfg))
    actor, state = load_actor(checkpoint, cfg)
    wrapper = actor.as_onnx(verbose=False).eval()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(
        wrapper,
        (torch.zeros(1, n_obs),),
        str(out_path),
        input_names=["obs"],
        output_names=["actions"],
        dynamic_axes={"obs": {0: "batch"}, "actions": {0: "batch"}},
        opset_version=ONNX_OPSET,
        dynamo=False,
    )
    model = onnx.load(str(out_path))
    model.ir_version = ONNX_IR_VERSION
    onnx.save(model, str(out_path))
    training = {
        "algorithm": "PPO (rsl_rl OnPolicyRunner)",
        "iterations": int(state.get("iter", -1)),
        "num_envs": cfg.get("num_envs"),
        "config": cfg,
    }
    manifest = build_manifest(out_path, mode, name, tuple(cfg["env"]["target_range_m"]), training,
                              history_steps=history_steps(cfg))
    write_manifest(out_path, manifest)
    runner = PolicyRunner.load(out_path)  # raises PolicyError if the runtime would refuse it
    with torch.no_grad():
        probe = torch.randn(4, n_obs)
        ref = wrapper(probe).numpy()
    got = np.stack([runner.act(p.numpy()) for p in probe])
    if not np.allclose(ref, got, atol=1e-4):
        raise RuntimeError("ONNX export differs from the PyTorch actor")
    log.info("exported %s (%s)", out_path, manifest["onnx_sha256"][:12])
    return out_path
