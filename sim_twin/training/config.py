"""The training config of a recipe (``sim_twin/configs/throw_<mode>.json`` or a committed
``policies/training/<run>/recipe.json``): its ``training`` section typed (:class:`TrainingSection`:
seed, std schedule, curriculum stage, gate start), read once when a run starts and refused
with a clear ValueError before anything is written. The ``env`` section is typed by
sim_twin.training.mjx_env.EnvConfig, the ``runner`` section is rsl_rl's.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields
from pathlib import Path

CONFIG_DIR = Path(__file__).parent.parent / "configs"


def _check_integer(value, name: str, at_least: int | None = None) -> None:
    """Raises ValueError unless ``value`` is an int (not a bool) and, with ``at_least``, >= it; the
    message names the config entry ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or (at_least is not None and value < at_least):
        bound = f" >= {at_least}" if at_least is not None else ""
        raise ValueError(f"{name} must be an integer{bound}, not {value!r}")


def _check_finite(value, name: str) -> None:
    """Raises ValueError unless ``value`` is a finite int or float (not a bool); the message names
    the config entry ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, not {value!r}")


@dataclass(frozen=True)
class StdSchedule:
    """Cap on the actor's action std: ``start`` -> ``end`` exponentially over ``iterations``,
    ``end`` after (config ``training.std_schedule``; CHOSEN values in configs/*.json).

    ``release_floor`` (0: none) is a lower bound on the std of the release flag (the last action):
    with a learned std the flag's std can shrink before the release is timed, after which the flag
    never crosses its 0.9 threshold and the policy stops throwing (seen from scratch in 3D)."""

    start: float
    end: float
    iterations: int
    release_floor: float = 0.0

    def cap(self, iteration: int) -> float:
        """The cap at ``iteration`` (>= 0)."""
        f = min(max(iteration, 0) / max(self.iterations, 1), 1.0)
        return float(self.start * (self.end / self.start) ** f)

    @classmethod
    def from_dict(cls, d: dict) -> StdSchedule:
        """Raises ValueError on unknown keys or non-positive values."""
        unknown = set(d) - {"start", "end", "iterations", "release_floor"}
        if unknown:
            raise ValueError(f"unknown std_schedule settings {sorted(unknown)}")
        s = cls(float(d["start"]), float(d["end"]), int(d["iterations"]), float(d.get("release_floor", 0.0)))
        if s.start <= 0 or s.end <= 0 or s.iterations < 1:
            raise ValueError(f"std_schedule needs start, end > 0 and iterations >= 1, got {d}")
        if not 0.0 <= s.release_floor <= s.end:
            raise ValueError(f"std_schedule.release_floor must be in [0, end], got {s.release_floor}")
        return s


@dataclass(frozen=True)
class CurriculumStage:
    """A change of the environment during training (config ``training.curriculum_stage``; the
    older spelling ``training.randomization_stage`` is read the same): from ``iteration`` on, new
    episodes draw from ``env.randomization`` with the entries of ``randomization`` in place of its
    own, and are rewarded by ``env.rewards`` with the entries of ``rewards`` in place of its own
    (either mapping may be empty, not both; CHOSEN values in configs/*.json).

    * A curriculum over randomisation width: the policy first learns to throw on the narrower
      ranges, then becomes robust on the wider ones.
    * A curriculum over reward terms: the candidate 2D recipe's ``{"err_3d": 0.0, "hold": 0.01,
      "hold_after_s": 5.0}`` from iteration 300 keeps the dense ``err_3d`` term while a run settles
      on its far-target throw style (with it 12 of 14 gamma 1.0 runs took the long style, without
      it 4 of 10) and then trades it for a cost on late releases (docs/training.md, "The hold cost
      after 5 s").

    Raises (from_dict):
        ValueError: unknown keys, a negative iteration, neither mapping given, widened entries that
            sim_twin.training.privileged.check_randomization refuses, or reward entries that
            sim_twin.training.rewards.RewardScales.from_dict refuses.
    """

    iteration: int
    randomization: dict
    rewards: dict

    @classmethod
    def from_dict(cls, d: dict, name: str = "training.curriculum_stage") -> CurriculumStage:
        from sim_twin.training.privileged import check_randomization
        from sim_twin.training.rewards import RewardScales

        unknown = set(d) - {"iteration", "randomization", "rewards"}
        if unknown or "iteration" not in d or not ({"randomization", "rewards"} & set(d)):
            raise ValueError(f"{name} needs 'iteration' and 'randomization' and/or 'rewards', got {sorted(d)}")
        _check_integer(d["iteration"], f"{name}.iteration", at_least=0)
        randomization, rewards = dict(d.get("randomization", {})), dict(d.get("rewards", {}))
        check_randomization(randomization, f"{name}.randomization")
        unknown_rewards = set(rewards) - {f.name for f in fields(RewardScales)}
        if unknown_rewards:
            raise ValueError(f"{name}.rewards: unknown reward settings {sorted(unknown_rewards)}")
        for key, value in rewards.items():
            _check_finite(value, f"{name}.rewards.{key}")
        return cls(d["iteration"], randomization, rewards)

    def env_dicts(self, env: dict) -> tuple[dict, dict]:
        """(before, after): the ``env`` mappings of the config before and after the stage. Both
        normalise the critic's privileged inputs over the stage's ranges (``privileged_ranges``,
        an explicit entry of the config kept), so the critic's inputs keep their scale.

        Raises:
            ValueError: the merged randomisation (sim_twin.training.privileged.Randomization) or
                rewards (RewardScales.from_dict, applied by EnvConfig.from_dict) are refused.
        """
        from sim_twin.training.mjx_env import EnvConfig
        from sim_twin.training.privileged import Randomization, trained_ranges

        wide = {**env.get("randomization", {}), **self.randomization}
        Randomization.from_dict(wide, "training.curriculum_stage (merged)")
        priv = {**trained_ranges(wide), **env.get("privileged_ranges", {})}
        before = {**env, "privileged_ranges": priv}
        after = {**before, "randomization": wide}
        if self.rewards:
            after["rewards"] = {**env.get("rewards", {}), **self.rewards}
        EnvConfig.from_dict(after)
        return before, after


@dataclass(frozen=True)
class DesiredKlStage:
    """A smaller step for PPO's adaptive learning rate late in a run (config
    ``training.desired_kl_stage``): from ``iteration`` on, rsl_rl's adaptive schedule aims at a
    mean KL divergence of ``desired_kl`` per update between the policy before and after it (the
    recipe's ``runner.algorithm.desired_kl`` before; it lowers the learning rate by 1.5× whenever an
    update's KL is over twice the aim and raises it when under half, rsl_rl PPO.update).

    Why: after a 2D run has met the bars its far-target bias keeps moving from checkpoint to
    checkpoint (``throw2d-scratch-n1``: nominal 10 m bias +0.017 to +0.157 m over 1650 iterations
    with the aim at 0.01 and the rate at 2-9·10⁻⁴; docs/training.md, "Site ranges after the style
    settles"), so the checkpoint the gate judges is one draw of a wandering policy. A smaller aim
    makes each update move the policy less. CHOSEN values in configs/*.json; untested values
    are marked so there.

    Raises (from_dict):
        ValueError: unknown keys, an iteration that is not an integer >= 0, a ``desired_kl`` that is
            not a finite number > 0.
    """

    iteration: int
    desired_kl: float

    @classmethod
    def from_dict(cls, d: dict, name: str = "training.desired_kl_stage") -> DesiredKlStage:
        if not isinstance(d, dict) or set(d) != {"iteration", "desired_kl"}:
            raise ValueError(f"{name} needs exactly 'iteration' and 'desired_kl', got {sorted(d) if isinstance(d, dict) else d!r}")
        _check_integer(d["iteration"], f"{name}.iteration", at_least=0)
        _check_finite(d["desired_kl"], f"{name}.desired_kl")
        if d["desired_kl"] <= 0:
            raise ValueError(f"{name}.desired_kl must be > 0, got {d['desired_kl']}")
        return cls(d["iteration"], float(d["desired_kl"]))


@dataclass(frozen=True)
class TrainingSection:
    """The config's ``training`` section, typed: what the run does beside the environment and PPO.

    ``seed`` (int or None: then ``--seed`` must give one, :func:`resolve_training`), ``std_schedule``
    (:class:`StdSchedule` or None: the learned std is only clamped by rsl_rl),
    ``curriculum_stage`` (:class:`CurriculumStage` or None: the environment stays as configured) and
    ``gate_from_iteration`` (int >= 0, default 0: the first iteration whose checkpoint the site-matrix
    gate judges), ``desired_kl_stage`` (:class:`DesiredKlStage` or None: PPO's KL aim stays the
    recipe's) and ``release_bias_init`` (float or None: the initial mean of the release flag, the
    actor's last output, set through its output layer's bias when a run starts from scratch; None
    leaves rsl_rl's initialisation, a mean near 0). With the flag's std at 0.6 and its 0.9 threshold
    a mean of 0 releases in 6.7 % of control steps, so the first episodes let go after about
    0.8 s (median); a mean of -0.35 releases in 1.9 % (median 3.0 s, near the 3.8-4.2 s of the
    long far-target throw the runs that met the bars settled on, docs/training.md).

    Two settings change how fast, not what, the run computes (both default false; docs/training.md,
    Throughput): ``per_iteration_syncs`` waits for the GPU once per rollout instead of at every
    environment step (sim_twin.training.runner.CallbackRunner, change 4: the same updates and logs),
    and ``tf32_matmul`` lets float32 matrix products on the GPU use TF32 tensor cores
    (``torch.backends.cuda.matmul.allow_tf32``; inputs rounded to 10 significant bits, products
    summed in float32), the actor's in the rollout and in the update alike, so the update recomputes
    the policy the rollout sampled from without the bfloat16 update's rounding gap.

    Raises (from_dict):
        ValueError: an unknown key (a misspelt setting would otherwise be ignored), a seed or
            ``gate_from_iteration`` that is not an integer (>= 0), both ``curriculum_stage`` and its
            older spelling ``randomization_stage``, ``per_iteration_syncs`` or ``tf32_matmul`` not a
            boolean, or what StdSchedule.from_dict, CurriculumStage.from_dict and
            DesiredKlStage.from_dict refuse.
    """

    seed: int | None = None
    std_schedule: StdSchedule | None = None
    curriculum_stage: CurriculumStage | None = None
    gate_from_iteration: int = 0
    release_bias_init: float | None = None
    per_iteration_syncs: bool = False
    tf32_matmul: bool = False
    desired_kl_stage: DesiredKlStage | None = None

    def env_dicts(self, env: dict) -> tuple[dict, dict]:
        """(before, after): the config's ``env`` mapping before and after the curriculum stage
        (:meth:`CurriculumStage.env_dicts`), or ``env`` twice without a stage.

        Raises:
            ValueError: the stage's merged randomisation or rewards are refused."""
        return self.curriculum_stage.env_dicts(env) if self.curriculum_stage else (env, env)

    @classmethod
    def from_dict(cls, d: dict) -> TrainingSection:
        known = [f.name for f in fields(cls)]
        unknown = set(d) - set(known) - {"randomization_stage"}
        if unknown:
            raise ValueError(f"unknown training settings {sorted(unknown)}; known: {known}")
        seed = d.get("seed")
        if seed is not None:
            _check_integer(seed, "training.seed")
        gate_from = d.get("gate_from_iteration", 0)
        _check_integer(gate_from, "training.gate_from_iteration", at_least=0)
        schedule = StdSchedule.from_dict(d["std_schedule"]) if "std_schedule" in d else None
        if "curriculum_stage" in d and "randomization_stage" in d:
            raise ValueError("training.curriculum_stage and training.randomization_stage (its older spelling) are one setting: give one")
        key = "curriculum_stage" if "curriculum_stage" in d else "randomization_stage"
        stage = CurriculumStage.from_dict(d[key], f"training.{key}") if key in d else None
        bias = d.get("release_bias_init")
        if bias is not None:
            _check_finite(bias, "training.release_bias_init")
        flags = {k: d.get(k, False) for k in ("per_iteration_syncs", "tf32_matmul")}
        for k, v in flags.items():
            if not isinstance(v, bool):
                raise ValueError(f"training.{k} must be true or false, not {v!r}")
        kl_stage = DesiredKlStage.from_dict(d["desired_kl_stage"]) if "desired_kl_stage" in d else None
        return cls(seed, schedule, stage, gate_from, None if bias is None else float(bias), **flags,
                   desired_kl_stage=kl_stage)


def load_config(mode: str, path: Path | None) -> dict:
    """The training config (env + runner + num_envs [+ training]) as a dict."""
    return json.loads((path or CONFIG_DIR / f"throw_{mode}.json").read_text())


def resolve_training(cfg: dict, seed_override: int | None) -> TrainingSection:
    """The config's ``training`` section, typed, with the run's training seed resolved: ``seed_override``
    (``--seed``) where given, else the recipe's ``training.seed``. The seed seeds the environments'
    start poses and randomisation (rank r of a multi-GPU run adds 1000 r); it is written into
    ``cfg["training"]["seed"]`` so that the run's config.json and model card record the seed
    actually used.

    Raises:
        ValueError: neither gives a seed, the seed is not an integer, a ``desired_kl_stage`` without
            rsl_rl's adaptive schedule (``runner.algorithm.schedule``, which the KL aim steers), or
            what :meth:`TrainingSection.from_dict` refuses in the section.
    """
    training = cfg.setdefault("training", {})
    seed = seed_override if seed_override is not None else training.get("seed")
    section = TrainingSection.from_dict({**training, "seed": seed})
    if section.seed is None:
        raise ValueError("the config has no training.seed: pass --seed")
    schedule_kind = cfg.get("runner", {}).get("algorithm", {}).get("schedule")
    if section.desired_kl_stage and schedule_kind != "adaptive":
        raise ValueError(f"training.desired_kl_stage needs runner.algorithm.schedule 'adaptive' (the KL aim steers it), not {schedule_kind!r}")
    training["seed"] = section.seed
    return section
