"""Reward terms of the throwing task (paper Sec. III-E), one function per term.

Each term function takes the step's :class:`RewardInputs` (one environment; vmapped by the
caller) and returns the term's *unscaled* value; :func:`reward_terms` scales them by
:class:`RewardScales` (the config's ``env.rewards``) and the reward is their sum
(:func:`total_reward`). The scaled terms are what the training logs as ``Reward/<term>``
(sim_twin.training.vec_env, rsl_rl's ``extras["log"]``), as MuJoCo Playground logs ``reward/<term>``.

    r = c1 r_delta_err + c2 r_err3d - c3 r_act_diff - c4 r_act  (+ terminal rewards)

The paper writes the landing kernel as exp(b2 err^2) with b2 > 0, which would grow with the
error; exp(-b2 err^2) is used (its evident intent). ``landing_fine`` (a second, sharper landing
kernel of width b3), ``landing_precise`` (a third, of width b4) and the per-step ``hold`` cost are our additions. All weights are CHOSEN (the paper gives none); their values
live in sim_twin/configs/throw_<mode>.json.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import jax.numpy as jnp


@dataclass(frozen=True)
class RewardScales:
    """Weights of the reward terms and widths of the exponential kernels (config ``env.rewards``).

    Attributes:
        delta_err: c1, per metre of newly reduced ball-to-target distance (2D + 3D).
        err_3d: c2, weight of the dense kernel exp(-b1 err3d^2).
        b1: width of the dense kernel [1/m^2].
        act_diff: c3, penalty per unit squared action change (actions clipped to [-1, 1]).
        act: c4, penalty per unit squared action after the gripper opened.
        failure: terminal reward of a collision / joint-limit / non-finite state (negative).
        landing: terminal weight of exp(-b2 impact_err^2) on landing.
        b2: width of the coarse landing kernel [1/m^2].
        landing_fine: terminal weight of exp(-b3 impact_err^2) on landing.
        b3: width of the fine landing kernel [1/m^2].
        landing_precise: terminal weight of exp(-b4 impact_err^2) on landing (0: off).
        b4: width of the precise landing kernel [1/m^2] (100: half reward at 8 cm, a gradient
            that still separates a 0.12 m from a 0.10 m spread, where exp(-16 e^2) is nearly flat).
        no_release: terminal reward of an episode that reaches its time limit without the gripper
            having been commanded open (negative; 0: off, and such an episode is a time-out whose
            value is bootstrapped). The site matrix counts a throw without release as a failure
            (sim_twin.evaluation.matrix, "no release within 10 s"); with a long discount horizon (gamma
            0.998) an unpunished time-out made waiting cheap (throw2d-scratch-p, policies/training/ARCHIVE.md).
        release_slope: terminal weight, per m/s, of how fast the landing point moved at the
            physics step the gripper opened (negative; 0: off), paid on a landing without failure.
            An opening-time error (release-delay jitter, sensor latency) moves the landing by
            about that speed times the error; the landing kernels pay for that spread only through
            single throws' noise, this term directly. Trained policies open where the landing
            point moves at 0.8-2.0 m/s on a nominal 10 m throw (reports/training_release_sensitivity_2d.json, lab notebook: reports/ARCHIVE.md);
            at -0.5 the term did not change which throw style a 2D run took (docs/training.md).
        hold: cost per control step that ends without the release having been commanded (>= 0;
            0: off). With gamma 1.0 no term made a later throw cost anything while the dense
            ``err_3d`` paid for every step the load was held near the target: the candidate 2D
            runs without forced release released later and later and ran 1-5 % of their episodes
            (at times up to 18 %) into the time limit (reports/training_release_noise_2d.md in the lab notebook, reports/ARCHIVE.md; docs/training.md,
            "γ 1.0 and the dense term"). A constant cost per held step is the time preference the
            discount gave, without the discount's share of the landing reward (CHOSEN value in the
            candidate 2D recipe).
        hold_after_s: episode time [s] before which ``hold`` charges nothing (0: from the first step).
            Charged from the first step, the cost favoured the short far-target throw: both runs of
            the candidate recipe with ``hold`` 0.01 from the start took it (throw2d-scratch-c0 and
            -c1, reports/training_scratch_2d_candidate.md in the lab notebook), where eight of ten γ 1.0 runs without it took
            the long one. Charged only after a grace longer than either style's release, it leaves
            the styles' returns alike and still charges a load held on and on (docs/training.md,
            "γ 1.0 and the dense term").
        early_release: cost per control step that ends with the release commanded while the episode is
            no older than ``early_release_s`` (>= 0; 0: off): a release commanded at t costs about
            early_release x (early_release_s - t) / 0.08 s, so an early swing's release pays more the
            earlier it comes and one after ``early_release_s`` nothing. Why (CHOSEN, untested on a GPU when
            written): the 2D runs that stalled with the curriculum stage release their 9.5-10 m throws on the
            first swing from some start poses and on a later one from others, the two groups landing
            0.15-0.17 m apart, where the runs that met the bars commit to one swing
            (policies/training/throw2d-scratch-n5/spread_sources_it675.json; docs/training.md, "Three more
            seeds of the fewer-winds recipe"); a cost on first-swing releases removes the choice.
        early_release_s: episode time [s] up to which a commanded release is charged ``early_release``
            (2.0 in throw_2d_sites_later_swing.json: the 2D policies' first-swing releases come at
            0.9-1.6 s, tests/benchmarks/spread_sources.py FIRST_SWING_S).
    """

    delta_err: float
    err_3d: float
    b1: float
    act_diff: float
    act: float
    failure: float
    landing: float
    b2: float
    landing_fine: float = 0.0
    b3: float = 4.0
    landing_precise: float = 0.0
    b4: float = 100.0
    no_release: float = 0.0
    release_slope: float = 0.0
    hold: float = 0.0
    hold_after_s: float = 0.0
    early_release: float = 0.0
    early_release_s: float = 0.0

    @classmethod
    def from_dict(cls, d: dict) -> RewardScales:
        """From the config's ``env.rewards`` mapping.

        Raises:
            ValueError: an unknown key (a typo would otherwise be ignored) or a missing weight.
        """
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown reward settings {sorted(unknown)}; known: {sorted(names)}")
        try:
            return cls(**{k: float(v) for k, v in d.items()})
        except TypeError as e:
            raise ValueError(f"reward settings incomplete: {e}") from None


class RewardInputs(NamedTuple):
    """Quantities of one environment after one control step (true state, not the measured one).

    err2_m, err3_m: horizontal / 3D distance ball (or gripper centre before opening) to target [m];
    err2_min_m, err3_min_m: their minima over the episode so far, before this step [m];
    action, prev_action: (num_actions,) policy outputs of this and the previous step;
    opened: the gripper has opened; failed: collision, joint limit or non-finite state;
    landed: the payload reached the ground this step; impact_err_m: horizontal impact error [m];
    unreleased_at_limit: the episode reached its time limit this step and the gripper was never
    commanded open; release_slope_mps: how fast the landing point moved when the gripper opened
    [m/s] (sim_twin.training.mjx_env.EnvState.release_slope); released: the release has been
    commanded by the end of this step (by the policy or the forced release; the gripper opens
    after the release delay); elapsed_s: episode time at the end of this step [s] (control steps
    times the control period).
    """

    err2_m: jnp.ndarray
    err3_m: jnp.ndarray
    err2_min_m: jnp.ndarray
    err3_min_m: jnp.ndarray
    action: jnp.ndarray
    prev_action: jnp.ndarray
    opened: jnp.ndarray
    failed: jnp.ndarray
    landed: jnp.ndarray
    impact_err_m: jnp.ndarray
    unreleased_at_limit: jnp.ndarray
    release_slope_mps: jnp.ndarray
    released: jnp.ndarray
    elapsed_s: jnp.ndarray


def reward_delta_err(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Progress: how much closer than ever before the ball came this step (2D + 3D) [m]."""
    return jnp.maximum(0.0, x.err2_min_m - x.err2_m) + jnp.maximum(0.0, x.err3_min_m - x.err3_m)


def reward_err_3d(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Dense kernel exp(-b1 err3d^2) in (0, 1]."""
    return jnp.exp(-w.b1 * x.err3_m**2)


def cost_act_diff(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Squared action change, actions clipped to [-1, 1] (returned negative: a cost)."""
    a, p = jnp.clip(x.action, -1.0, 1.0), jnp.clip(x.prev_action, -1.0, 1.0)
    return -jnp.sum((a - p) ** 2)


def cost_act(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Squared action after the gripper opened (returned negative: a cost)."""
    return -jnp.sum(jnp.clip(x.action, -1.0, 1.0) ** 2) * x.opened


def reward_failure(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """1 on a failure (collision, joint limit, non-finite state), else 0; the scale is negative."""
    return x.failed.astype(jnp.float32)


def reward_landing(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Coarse landing kernel exp(-b2 impact_err^2) on a landing without failure, else 0."""
    return jnp.where(x.landed & ~x.failed, jnp.exp(-w.b2 * x.impact_err_m**2), 0.0)


def reward_landing_fine(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Fine landing kernel exp(-b3 impact_err^2) on a landing without failure, else 0."""
    return jnp.where(x.landed & ~x.failed, jnp.exp(-w.b3 * x.impact_err_m**2), 0.0)


def reward_landing_precise(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """Precise landing kernel exp(-b4 impact_err^2) on a landing without failure, else 0."""
    return jnp.where(x.landed & ~x.failed, jnp.exp(-w.b4 * x.impact_err_m**2), 0.0)


def reward_no_release(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """1 when the episode ends at its time limit without a release command, else 0; the scale is negative."""
    return x.unreleased_at_limit.astype(jnp.float32)


def cost_release_slope(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """The landing point's speed at the opening [m/s] on a landing without failure, else 0; the scale is negative."""
    return jnp.where(x.landed & ~x.failed, x.release_slope_mps, 0.0)


def cost_hold(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """1 for a control step that ends after ``hold_after_s`` of episode time with the release not yet
    commanded, else 0 (returned negative: a cost)."""
    return -(~x.released & (x.elapsed_s > w.hold_after_s)).astype(jnp.float32)


def cost_early_release(x: RewardInputs, w: RewardScales) -> jnp.ndarray:
    """1 for a control step that ends with the release commanded at an episode time no later than
    ``early_release_s``, else 0 (returned negative: a cost)."""
    return -(x.released & (x.elapsed_s <= w.early_release_s)).astype(jnp.float32)


REWARD_TERMS = {
    "delta_err": reward_delta_err,
    "err_3d": reward_err_3d,
    "act_diff": cost_act_diff,
    "act": cost_act,
    "failure": reward_failure,
    "landing": reward_landing,
    "landing_fine": reward_landing_fine,
    "landing_precise": reward_landing_precise,
    "no_release": reward_no_release,
    "release_slope": cost_release_slope,
    "hold": cost_hold,
    "early_release": cost_early_release,
}
"""Term name (= its scale's name in RewardScales) -> unscaled term function."""


def reward_terms(x: RewardInputs, w: RewardScales) -> dict[str, jnp.ndarray]:
    """Every term scaled by its weight, keyed by REWARD_TERMS' names (scalars per environment)."""
    return {name: getattr(w, name) * fn(x, w) for name, fn in REWARD_TERMS.items()}


def diverged(terms: dict[str, jnp.ndarray]) -> jnp.ndarray:
    """Whether the scaled terms' sum is not finite (a diverged state: non-finite joint positions make
    the distance terms NaN), per environment (bool, the terms' shape)."""
    return ~jnp.isfinite(sum(terms.values()))


def total_reward(terms: dict[str, jnp.ndarray], failure_reward: float) -> jnp.ndarray:
    """Sum of the scaled terms; where it is not finite (:func:`diverged`) the failure reward."""
    return jnp.where(diverged(terms), failure_reward, sum(terms.values()))
