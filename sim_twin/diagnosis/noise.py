"""Measurement noise of a log and the noise-aware residual statistics of the diagnosis.

Every residual (logged - replayed) is expressed in units of its noise, so that a channel that
matches up to its noise contributes about one unit per degree of freedom (chi-square):

* trajectory channels (joint encoders, gripper IMU; payload tracking when logged): white
  noise sigma per sample measured from the log itself, robustly from second differences of the
  nominal residual (white noise: E (e[t+1] - 2 e[t] + e[t-1])^2 = 6 sigma^2, pooled over the
  throws; the smooth part of a model error differences away at 100 Hz, what is left of it only
  makes sigma larger, i.e. the test more cautious), floored at FLOOR. The samples are averaged in blocks
  of BLOCK_ROWS rows within each phase: one degree of freedom per block,
  z = sum(e) / (sigma sqrt(n)).
* impact (downrange, crossrange), one degree of freedom each per throw: variance = the impact
  sensor's (declared ``sensors.impact_sigma_m``, else measured as the scatter of the nominal
  impact residual about its mean) plus the release-jitter spread the replay predicts.
* release delay (only with a logged payload-free flag): variance = jitter^2 + tick^2 / 12.

A channel (or channel and phase) has a gap when its chi-square exceeds its degrees of freedom D
by more than Z_GAP standard deviations AND by more than R_GAP D (the second guards against noise
that is not quite white). "Z_GAP standard deviations" is a tail probability, that of Z_GAP
sigma of a normal (P_GAP, 2.9e-7 at 5 sigma), taken from the chi-square distribution itself
(:func:`gap_test`), not from the normal approximation D + Z_GAP sqrt(2 D): a chi-square with few
degrees of freedom is skewed to the right, and on the impact channels (one degree of freedom per
throw, ~26 in 30 throws) the approximation's threshold 62 is exceeded by noise alone with
probability 9e-5, 300 times the intended level (the exact threshold is 79). Above 270 degrees
of freedom (a trajectory channel of 30 throws has about 400) the R_GAP rule is the stricter one
and the two agree.

The chi-square excess is a weak test of a small systematic shift: a mean impact shift of
k sigma / sqrt(N) adds only k^2 to a chi-square with N degrees of freedom. Every channel's mean
residual is therefore also tested for a bias (:func:`bias_tests`): a one-sample t-test over the
throws of the per-throw standardised mean residual (:meth:`scoring.Scorer.signed`), two-sided,
with Holm's step-down correction over the channels tested (S. Holm, "A simple sequentially
rejective multiple test procedure", Scand. J. Statist. 6 (1979) 65-70) at family-wise level
BIAS_ALPHA. A channel with a significant bias has a gap as well.

On the trajectory channels the test asks for a *material* bias: the null hypothesis is "the mean
residual per sample is within BIAS_MARGIN[kind] of the channel's noise sigma" (a minimum-effect
test: p = P(T > (|m| - d) / se) + P(T > (|m| + d) / se), T Student's t with N - 1 degrees of
freedom, d the margin in units of M; d = 0 gives the plain two-sided t-test). The replay of a
trajectory is not exact: on noise-only logs of the simulated machine the per-sample mean residual
of some channels sits a few hundredths of their sigma off zero, consistently over hundreds of
throws (reports/diagnosis_noise_bias.txt), a systematic the noise model does not hold; with
enough throws a plain t-test finds it. The impact and the logged opening delay keep d = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from runtime.machine import JOINT_NAMES

BLOCK_ROWS = 10
Z_GAP = 5.0
R_GAP = 0.5
P_GAP = 2.866515718791933e-07
"""One-sided tail probability of Z_GAP sigma of a normal (``scipy.stats.norm.sf(Z_GAP)``): the
false-alarm probability of one channel's excess test (:func:`gap_test`)."""
FLOOR = {"q.active": 2e-4, "qd.active": 2e-3, "q.passive": 5e-4, "qd.passive": 5e-3, "payload": 2e-3}
"""Noise floors (rad, m, rad/s, m/s): encoder / IMU resolution of a noise-free log (CHOSEN)."""
MIN_IMPACT_SIGMA_M = 0.01
BIAS_ALPHA = 0.01
"""Family-wise false-alarm probability of the bias tests of one diagnosis (CHOSEN: one nominal
dataset in a hundred shows a bias gap from noise alone)."""
BIAS_MARGIN = {"q": 0.1, "qd": 0.02}
"""Immaterial per-sample bias of a trajectory channel, in units of its noise sigma, per kind
(positions, rates). MEASURED then CHOSEN: twice the largest systematic per-sample mean residual on
noise-only logs of the simulated machine (positions 0.054 sigma, rates 0.010 sigma on 555 throws,
reports/diagnosis_noise_bias.txt)."""
POWER = 0.8
"""Detection probability at which a detectable size is stated (CHOSEN, the usual 80 %)."""


def trajectory_channels() -> list[tuple[str, str, int]]:
    """(channel, kind, joint index) of the 12 joint channels: q.<joint>, qd.<joint>."""
    out = []
    for j, name in enumerate(JOINT_NAMES):
        out.append((f"q.{name}", "q", j))
        out.append((f"qd.{name}", "qd", j))
    return out


TRAJ = trajectory_channels()
CHANNELS = [c for c, _, _ in TRAJ] + ["payload.held", "payload.flight", "release.delay", "impact.downrange", "impact.crossrange", "impact.spread"]
"""``impact.spread`` is the Gaussian log-likelihood's log-variance term of the impact, log(v /
sigma_sensor^2), for fits whose predicted release jitter changes the impact variance v; it has
no degrees of freedom and takes no part in gap tests."""
CH_INDEX = {c: i for i, c in enumerate(CHANNELS)}
PHASES = ("swing", "release", "flight")


def group_of(channel: str) -> str:
    """Reporting group: active, passive, payload, release, impact."""
    if channel.startswith(("q.", "qd.")):
        return "passive" if channel.split(".", 1)[1].startswith("gripper") else "active"
    return channel.split(".", 1)[0]


def floor_of(channel: str) -> float:
    g = group_of(channel)
    if g == "payload":
        return FLOOR["payload"]
    return FLOOR[f"{channel.split('.', 1)[0]}.{g}"]


@dataclass
class NoiseModel:
    """Noise per channel.

    Attributes:
        sigma: trajectory channel -> white noise sigma per sample (channel units).
        impact_sigma_m: impact sensor sigma per horizontal axis, m.
        source: channel -> "measured" | "declared" | "floor".
    """

    sigma: dict[str, float]
    impact_sigma_m: float
    source: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"sigma": self.sigma, "impact_sigma_m": self.impact_sigma_m, "source": self.source}


def gap_test(S: float, D: float) -> tuple[bool, float]:
    """(gap?, excess z-score) of a chi-square S with D degrees of freedom (see module doc).

    The gap: S > (1 + R_GAP) D and P(chi2_D >= S) < P_GAP (the exact chi-square tail,
    ``scipy.stats.chi2.sf``). The returned z is the excess in standard deviations of the
    chi-square, (S - D) / sqrt(2 D) (reported as ``excess_z``; the swing gate
    ``forward.SWING_Z`` compares it), not the z of that tail probability.
    """
    from scipy.stats import chi2

    if D <= 0:
        return False, 0.0
    z = (S - D) / np.sqrt(2 * D)
    return bool(S > (1 + R_GAP) * D and z > 0 and chi2.sf(S, D) < P_GAP), float(z)


def worse_tolerance(D: np.ndarray) -> np.ndarray:
    """How much a channel's chi-square may grow before it counts as worse beyond its noise:
    2 standard deviations of a chi-square with D degrees of freedom, at least 2."""
    return np.maximum(2.0 * np.sqrt(2.0 * np.asarray(D, dtype=float)), 2.0)


def bias_tests(M: np.ndarray, D: np.ndarray, alpha: float = BIAS_ALPHA, margin: np.ndarray | None = None) -> dict[str, dict]:
    """Bias test of every channel with data (module doc).

    Args:
        M: (N, C) per-throw standardised mean residuals (:meth:`scoring.Scorer.signed`).
        D: (N, C, P) degrees of freedom (a channel is tested where it has data in >= 3 throws).
        alpha: family-wise level (Holm).
        margin: (N, C) immaterial |E M| per throw (:attr:`scoring.Scorer.bias_margin`), or None
            for 0 everywhere (the plain t-test).

    Returns:
        channel -> {"mean": mean of M (noise units), "sd", "t": plain t statistic, "margin":
        the immaterial mean (units of M), "t_material": (|mean| - margin) / se, "p": p of
        "|E M| > margin", "p_holm": Holm-adjusted p, "bias": bool (p_holm < alpha), "n": throws}.

    Raises:
        ValueError: margin of another shape than M, or negative.
    """
    from scipy.stats import t as student_t

    if margin is not None and (np.shape(margin) != np.shape(M) or np.any(np.asarray(margin) < 0)):
        raise ValueError(f"margin must be a non-negative array of M's shape {np.shape(M)}, got shape {np.shape(margin)}")
    has = D.sum(axis=2) > 0  # (N, C)
    rows = {}
    for c, name in enumerate(CHANNELS):
        m = M[has[:, c], c]
        if len(m) < 3:
            continue
        d = float(np.mean(margin[has[:, c], c])) if margin is not None else 0.0
        sd = float(np.std(m, ddof=1))
        se = sd / np.sqrt(len(m))
        tt = float(m.mean() / se) if sd > 0 else 0.0
        tm = float((abs(m.mean()) - d) / se) if sd > 0 else 0.0
        p = float(student_t.sf(tm, len(m) - 1) + student_t.sf((abs(m.mean()) + d) / se, len(m) - 1)) if sd > 0 else 1.0
        rows[name] = {"mean": float(m.mean()), "sd": sd, "t": tt, "margin": d, "t_material": tm, "p": min(p, 1.0), "n": len(m)}
    order = sorted(rows, key=lambda k: rows[k]["p"])
    running = 0.0
    for i, name in enumerate(order):
        running = max(running, min(1.0, (len(order) - i) * rows[name]["p"]))
        rows[name]["p_holm"] = running
        rows[name]["bias"] = bool(running < alpha)
    return rows


def detectable_mean(sd: float, n: int, tests: int, alpha: float = BIAS_ALPHA, power: float = POWER, margin: float = 0.0) -> float:
    """Smallest mean (noise units of M) the bias test finds with probability ``power`` in n
    throws, at the Bonferroni level alpha / tests (Holm's first step; normal approximation):
    margin + (z_{1 - alpha / (2 tests)} + z_power) sd / sqrt(n)."""
    from scipy.stats import norm

    return float(margin + (norm.isf(alpha / (2 * max(tests, 1))) + norm.ppf(power)) * sd / np.sqrt(max(n, 1)))
