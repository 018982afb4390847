"""The actor network kept in float32 inside rsl_rl's bfloat16 update.

rsl_rl's ``algorithm.use_mixed_precision`` runs the whole PPO update (actor and critic forward
passes, losses) under ``torch.autocast(dtype=torch.bfloat16)``, while the rollout that recorded the
old log-probabilities and distribution parameters ran in float32 (rsl_rl 5.5, ``PPO.act`` outside
autocast, ``PPO.update`` inside). bfloat16 keeps 8 significant bits, so the policy mean the update
recomputes is off from the rollout's by its rounding: about 0.004 rms for a trained 2D actor (actions
of about 0.5-1). Against a Gaussian of standard deviation σ that is a KL divergence of about
Σ δ²/(2σ²) per sample and a log-ratio error of about δ/σ per action: at the recipes' std floor
σ = 0.05 the rounding alone gives a KL of 0.011-0.014, above rsl_rl's adaptive-schedule target
``desired_kl`` 0.01, so the learning rate can only fall, and 12-18 % of the ratios leave PPO's
clip range 0.2 with no change to the weights (``reports/training_policy_rounding_2d.md``, in the lab notebook: reports/ARCHIVE.md).

``Float32MLPModel`` runs the actor with autocast switched off, so the update's policy mean is the
rollout's to the bit and only the critic's arithmetic is bfloat16 (a value off by its rounding,
at most 0.06 for values under 32, where the 2D episode returns are about 25, changes the value loss
by far less than its size, 1.3-2.1 in the runs of reports/training_policy_rounding_2d.md, in the lab notebook).
Select it in a recipe with ``runner.actor.class_name`` ``"sim_twin.training.models:Float32MLPModel"``
(rsl_rl resolves "module:Class"); its state dict is MLPModel's, so checkpoints resume and export
(sim_twin.training.export builds an MLPModel) either way.
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel

FLOAT32_ACTOR = "sim_twin.training.models:Float32MLPModel"
"""The ``runner.actor.class_name`` that selects :class:`Float32MLPModel`."""


class Float32MLPModel(MLPModel):
    """rsl_rl's MLPModel whose forward pass (normaliser, MLP, distribution parameters) always runs
    in float32, also inside ``torch.autocast``: outputs (num_envs, num_actions) float32, the
    distribution's mean and std float32, bit-identical to the model outside autocast. Arguments and
    behaviour otherwise as ``rsl_rl.models.MLPModel``."""

    def forward(self, obs, masks=None, hidden_state=None, stochastic_output: bool = False) -> torch.Tensor:
        """MLPModel.forward with autocast disabled for this module's device type."""
        device_type = next(self.parameters()).device.type
        with torch.autocast(device_type=device_type, enabled=False):
            return super().forward(obs, masks=masks, hidden_state=hidden_state, stochastic_output=stochastic_output)
