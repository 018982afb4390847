"""Resume an rsl_rl checkpoint whose critic saw fewer inputs (adding the privileged group).

A checkpoint trained with ``runner.obs_groups.critic = ["policy"]`` is resumed with a critic on
["policy", "privileged"] (sim_twin.training.privileged). rsl_rl's MLPModel concatenates the groups in the
listed order, so the new inputs are the LAST columns of the critic's input. The surgery keeps the
value function exactly:

* critic ``mlp.0.weight`` (hidden, n_old) -> (hidden, n_new): zero columns appended, so the new
  inputs contribute nothing until training moves them; every other critic tensor is unchanged;
* critic ``obs_normalizer._mean`` / ``_var`` / ``_std`` (1, n_old) -> (1, n_new): appended with
  mean 0, var 1, std 1 (the privileged inputs are already scaled to about [-1, 1]);
  ``obs_normalizer.count`` is kept, so the old statistics stay as they were;
* the actor (weights, normaliser, action std) is not touched;
* Adam state (``optimizer_state_dict``): per parameter, by index. Every entry whose shape still
  matches is kept. The widened weight's ``exp_avg`` / ``exp_avg_sq`` get zero columns (as if
  those inputs had had zero gradient so far) and its ``step`` is kept; with bias correction ~1
  the first Adam update of a new column is then about sqrt(10) * lr * sign(grad), falling to
  ~lr within some ten updates. Any other entry whose shape does not match is dropped (Adam
  restarts it from zero); there are none for the widening above.

rsl_rl 5.5 checkpoint keys (torch.load of tests/data/policy_only_critic_2d.pt):
``actor_state_dict``, ``critic_state_dict``, ``optimizer_state_dict`` (one Adam param group: the
actor's parameters, then the critic's: std_param, mlp.{0,2,4}.{weight,bias} of each), ``iter``,
``infos``. Normaliser buffers: ``obs_normalizer._mean``, ``._var``, ``._std`` (1, n) and
``.count`` ().
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

log = logging.getLogger(__name__)

FIRST_LAYER = "mlp.0.weight"
NORMALISER_FILL = {"obs_normalizer._mean": 0.0, "obs_normalizer._var": 1.0, "obs_normalizer._std": 1.0}
ADAM_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")


def _pad_columns(t: torch.Tensor, n_new: int, value: float) -> torch.Tensor:
    """t (..., n_old) with (n_new - n_old) columns of ``value`` appended on the last axis."""
    pad = torch.full((*t.shape[:-1], n_new - t.shape[-1]), value, dtype=t.dtype, device=t.device)
    return torch.cat([t, pad], dim=-1)


def widen_critic(
    ckpt: Mapping, critic_state: Mapping[str, torch.Tensor], param_shapes: Sequence[torch.Size]
) -> tuple[dict, list[str]]:
    """Fit an older checkpoint to a critic with more inputs (see the module docstring).

    Args:
        ckpt: the checkpoint dict (torch.load of rsl_rl's checkpoint.pt); not modified.
        critic_state: state_dict of the critic being resumed (the target shapes).
        param_shapes: shapes of the optimiser's parameters in its order (all param groups).

    Returns:
        (checkpoint dict ready for PPO.load with strict=True, notes on what was changed; empty
        when nothing had to change).

    Raises:
        ValueError: the critics differ in anything but the first layer's input width, the new
            critic has fewer inputs, or the optimiser's parameter count differs.
    """
    old = ckpt["critic_state_dict"]
    if set(old) != set(critic_state):
        raise ValueError(f"critic keys differ: {sorted(set(old) ^ set(critic_state))}")
    n_old, n_new = old[FIRST_LAYER].shape[1], critic_state[FIRST_LAYER].shape[1]
    widened = {FIRST_LAYER, *(k for k in NORMALISER_FILL if k in old)}
    for k, v in old.items():
        if k not in widened and v.shape != critic_state[k].shape:
            raise ValueError(f"critic {k}: {tuple(v.shape)} cannot become {tuple(critic_state[k].shape)}")
    if n_new < n_old:
        raise ValueError(f"the critic has {n_new} inputs, the checkpoint's {n_old}: cannot narrow")
    if n_new == n_old:
        return dict(ckpt), []
    critic = dict(old)
    critic[FIRST_LAYER] = _pad_columns(old[FIRST_LAYER], n_new, 0.0)
    for k, fill in NORMALISER_FILL.items():
        if k in old:
            critic[k] = _pad_columns(old[k], n_new, fill)
    notes = [f"critic input {n_old} -> {n_new}: {FIRST_LAYER} zero columns, normaliser mean 0 / var 1, count kept"]
    out = dict(ckpt, critic_state_dict=critic)
    if "optimizer_state_dict" in ckpt:
        out["optimizer_state_dict"], opt_notes = _fit_optimizer(ckpt["optimizer_state_dict"], param_shapes)
        notes += opt_notes
    return out, notes


def _fit_optimizer(opt: Mapping, param_shapes: Sequence[torch.Size]) -> tuple[dict, list[str]]:
    """Adam state dict with each entry fitted to ``param_shapes`` (module docstring)."""
    n_saved = sum(len(g["params"]) for g in opt["param_groups"])
    if n_saved != len(param_shapes):
        raise ValueError(f"optimiser had {n_saved} parameters, now {len(param_shapes)}")
    state, notes = {}, []
    for idx, st in opt["state"].items():
        shape = torch.Size(param_shapes[idx])
        ref = st.get("exp_avg")
        if ref is None or ref.shape == shape:
            state[idx] = st
        elif ref.dim() == 2 and ref.shape[0] == shape[0] and ref.shape[1] < shape[1]:
            state[idx] = {k: (_pad_columns(v, shape[1], 0.0) if k in ADAM_MOMENTS else v) for k, v in st.items()}
            notes.append(f"optimiser param {idx}: Adam moments {tuple(ref.shape)} -> {tuple(shape)}, zero columns, step kept")
        else:
            notes.append(f"optimiser param {idx}: state {tuple(ref.shape)} does not fit {tuple(shape)}, reset")
    return dict(opt, state=state), notes


def match_std_parameter(actor_state: dict, actor_cfg: dict) -> tuple[dict, list[str]]:
    """Convert the actor's std parameter between rsl_rl's parameterisations.

    A checkpoint with ``distribution.std_param`` (std_type "scalar") loaded into a config with
    std_type "log" gets ``distribution.log_std_param`` = log of the std clamped to the config's
    ``std_range``, and the reverse; the std the policy samples with is unchanged where it lies in
    the range. Returns (actor state, notes); the state is returned as is when nothing differs.
    """
    dist = actor_cfg.get("distribution_cfg") or {}
    std_type = dist.get("std_type", "scalar")
    lo, hi = dist.get("std_range", (1e-6, 1e6))
    lo = max(lo, 1e-6)
    if std_type == "log" and "distribution.std_param" in actor_state:
        out = dict(actor_state)
        out["distribution.log_std_param"] = torch.log(out.pop("distribution.std_param").clamp(lo, hi))
        return out, ["actor std: scalar -> log parameter"]
    if std_type == "scalar" and "distribution.log_std_param" in actor_state:
        out = dict(actor_state)
        out["distribution.std_param"] = torch.exp(out.pop("distribution.log_std_param")).clamp(lo, hi)
        return out, ["actor std: log -> scalar parameter"]
    return actor_state, []


def resume(runner, path: Path, device: str) -> list[str]:
    """Load ``path`` into an rsl_rl OnPolicyRunner, widening the critic where needed.

    Sets ``runner.current_learning_iteration`` to the checkpoint's ``iter`` (as
    OnPolicyRunner.load does). Returns the notes of widen_critic (logged as well). Raises
    ValueError as widen_critic.
    """
    ckpt = torch.load(path, weights_only=False, map_location=device)
    target = runner.alg.save()["critic_state_dict"]
    shapes = [p.shape for g in runner.alg.optimizer.param_groups for p in g["params"]]
    ckpt, notes = widen_critic(ckpt, target, shapes)
    ckpt["actor_state_dict"], std_notes = match_std_parameter(ckpt["actor_state_dict"], runner.cfg["actor"])
    notes += std_notes  # the Adam moments of the std parameter are kept (same shape)
    for n in notes:
        log.info("resume %s: %s", path, n)
    runner.alg.load(ckpt, None, strict=True)
    runner.current_learning_iteration = ckpt["iter"]
    return notes
