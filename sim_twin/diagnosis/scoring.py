"""Noise-scaled chi-square of replays against the log, per throw, channel and phase.

``Scorer(throws, noise).score(replays)`` returns S (N, C, P): for throw n, channel c
(:data:`noise.CHANNELS`) and phase p (:data:`noise.PHASES`) the sum of squared noise-scaled
residuals; ``Scorer.D`` (N, C, P) holds the matching degrees of freedom. Phase boundaries are
fixed per throw (release command; the logged opening, else the nominal twin's most likely
opening row) so that S of different candidates compare sample by sample.
"""

from __future__ import annotations

import math

import numpy as np

from runtime.machine import JOINT_NAMES
from runtime.throw_geometry import impact_errors
from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import replay as rp
from sim_twin.diagnosis.dataset import TICK_S, LoggedThrow
from sim_twin.diagnosis.replay import REST_ROWS, Replay, open_row
from sim_twin.twin.profile import RealityProfile

N_TRAJ = len(nz.TRAJ)
C = len(nz.CHANNELS)
P = len(nz.PHASES)
IMPACT = [nz.CH_INDEX["impact.downrange"], nz.CH_INDEX["impact.crossrange"]]
DELAY = nz.CH_INDEX["release.delay"]
SPREAD = nz.CH_INDEX["impact.spread"]


def _blocks(L: int, bounds: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block starts, lengths and phases of rows [0, L) cut at ``bounds`` (phase ends)."""
    starts, lens, phases = [], [], []
    a = 0
    for p, b in enumerate(bounds):
        b = min(max(b, a), L)
        for s in range(a, b, nz.BLOCK_ROWS):
            starts.append(s)
            lens.append(min(nz.BLOCK_ROWS, b - s))
            phases.append(p)
        a = b
    return np.array(starts, dtype=int), np.array(lens, dtype=float), np.array(phases, dtype=int)


def directions(target_m: np.ndarray) -> np.ndarray:
    """(2, 2) unit vectors (downrange, crossrange left positive) of a target's line, x-y."""
    d = np.asarray(target_m[:2], dtype=float)
    d = d / max(np.linalg.norm(d), 1e-9)
    return np.array([d, [-d[1], d[0]]])


def impact_residuals(throws: list[LoggedThrow], reps: list[Replay]) -> tuple[np.ndarray, np.ndarray]:
    """(residual (N, 2) downrange/crossrange m, jitter variance (N, 2) m^2) of the measured
    impact against the replay (released at the logged opening when logged, else the
    expectation over the model's opening rows)."""
    r = np.zeros((len(throws), 2))
    v = np.zeros((len(throws), 2))
    for n, (th, rep) in enumerate(zip(throws, reps)):
        fl = rep.cond if th.open_row is not None else rep.pred
        r[n] = np.subtract(impact_errors(th.target_m, th.impact_m), impact_errors(th.target_m, fl["impact_m"]))
        U = directions(th.target_m)
        v[n] = np.einsum("ij,jk,ik->i", U, fl.get("impact_cov_m2", np.zeros((2, 2))), U)
    return r, v


class Scorer:
    """Scores replays of one throw set under one noise model.

    Args:
        throws: N logged throws.
        noise: the noise model (:func:`estimate_noise`).

    Attributes:
        D: (N, C, P) degrees of freedom.
        bias_margin: (N, C) the immaterial mean of :meth:`signed` per throw (units of M), the
            margin of the bias tests (:func:`noise.bias_tests`): noise.BIAS_MARGIN sqrt(L) on
            the trajectory channels (L scored rows), 0 on the impact and the opening delay.
    """

    def __init__(self, throws: list[LoggedThrow], noise: nz.NoiseModel):
        self.throws, self.noise = throws, noise
        nominal = RealityProfile()
        self.sig = np.array([noise.sigma[c] for c, _, _ in nz.TRAJ])
        # variance of the replay's start-position error relative to each channel's sigma^2:
        # active joints averaged over REST_ROWS rows; gripper_pitch hangs plumb below boom + dipper
        sig_q = {j: noise.sigma[f"q.{name}"] for j, name in enumerate(JOINT_NAMES)}
        tau2 = np.zeros(N_TRAJ)
        for i, (_c, kind, j) in enumerate(nz.TRAJ):
            if kind == "q" and j < 4:
                tau2[i] = sig_q[j] ** 2 / REST_ROWS
            elif kind == "q" and j == 4:
                tau2[i] = (sig_q[1] ** 2 + sig_q[2] ** 2) / REST_ROWS
        self.tau2_rel = tau2 / self.sig**2
        self.layout = []
        D = np.zeros((len(throws), C, P))
        for n, th in enumerate(throws):
            L = rp.score_rows(th)
            o = th.open_row if th.open_row is not None else open_row(th, nominal.release_delay_mean_s)
            st, ln, ph = _blocks(L, [th.cmd_row, o, L])
            self.layout.append((st, ln, ph))
            for p in range(P):
                D[n, :N_TRAJ, p] = np.sum(ph == p)
            D[n, IMPACT, 2] = 1
            if th.open_row is not None:
                D[n, DELAY, 1] = 1
        self.D = D
        # the immaterial mean of M per throw (noise.BIAS_MARGIN): a per-sample bias b (units of
        # sigma) over L scored rows gives M = b sqrt(L); the impact and the opening delay: 0
        rows = np.array([max(rp.score_rows(th), 1) for th in throws], dtype=float)
        self.bias_margin = np.zeros((len(throws), C))
        self.bias_margin[:, :N_TRAJ] = np.sqrt(rows)[:, None] * np.array([nz.BIAS_MARGIN[kind] for _c, kind, _j in nz.TRAJ])[None, :]

    def block_z(self, n: int, rep: Replay) -> np.ndarray:
        """(blocks, 12) noise-scaled block residuals of throw n's trajectory channels (TRAJ order:
        q.j, qd.j): each block's summed residual (logged - replayed) over sigma sqrt(rows), so its
        square is the block's chi-square; the blocks are :attr:`layout`'s."""
        th = self.throws[n]
        L = rp.score_rows(th)
        e = np.concatenate([th.q[:L] - rep.meas_q[:L], th.qd[:L] - rep.meas_qd[:L]], axis=1)  # (L, 12): q0..q5, qd0..qd5
        e = e[:, np.ravel(np.column_stack([np.arange(6), 6 + np.arange(6)]))]  # TRAJ order: q.j, qd.j
        st, ln, _ = self.layout[n]
        return np.add.reduceat(e, st, axis=0) / (self.sig * np.sqrt(ln)[:, None])

    def residuals(self, reps: list[Replay]) -> np.ndarray:
        """(K,) the noise-scaled residual vector of replays of the N throws: every throw's block
        residuals (:meth:`block_z`, channels with data) and its impact residuals over their
        sigma. Its squared norm is :meth:`score`'s total without the start-state correction, the
        logged opening delay and the impact-spread term (for least-squares engines that need
        residuals, e.g. ``mujoco.minimize.least_squares``)."""
        has = self.D.sum(axis=(0, 2))[:N_TRAJ] > 0
        r, v = impact_residuals(self.throws, reps)
        parts = [self.block_z(n, rep)[:, has].ravel() for n, rep in enumerate(reps)]
        return np.concatenate(parts + [(r / np.sqrt(self.noise.impact_sigma_m**2 + v)).ravel()])

    def score(self, reps: list[Replay]) -> np.ndarray:
        """S (N, C, P) for replays of the N throws (same order)."""
        S = np.zeros((len(self.throws), C, P))
        for n, (th, rep) in enumerate(zip(self.throws, reps)):
            z = self.block_z(n, rep)  # (blocks, 12) block means / their sigma
            st, ln, ph = self.layout[n]
            z2 = z * z
            for p in range(P):
                S[n, :N_TRAJ, p] = z2[ph == p].sum(axis=0)
            # position channels: the start state's own error (a constant per throw, variance tau^2)
            # is a random effect; chi2 = m' (s^2 I + tau^2 11')^-1 m (Sherman-Morrison)
            a = self.tau2_rel  # (12,): tau^2 / sigma^2
            u = np.sum(z * np.sqrt(ln)[:, None], axis=0)  # sum m_i / s_i^2 in units of 1/sigma
            corr = a * u * u / (1.0 + a * ln.sum())
            for p in range(P):
                S[n, :N_TRAJ, p] -= corr * (np.sum(ph == p) / len(ph))
            if (open_delay_s := th.open_delay_s) is not None:  # None without a logged opening
                d = open_delay_s - expected_logged_delay(rep.delay_mean_s, rep.delay_std_s)
                S[n, DELAY, 1] = d * d / (max(rep.delay_std_s, 1e-3) ** 2 + TICK_S**2 / 12)
        r, v = impact_residuals(self.throws, reps)
        var = self.noise.impact_sigma_m**2 + v
        S[:, IMPACT, 2] = r * r / var
        S[:, SPREAD, 2] = np.sum(np.log(var / self.noise.impact_sigma_m**2), axis=1)
        return S


    def signed(self, reps: list[Replay]) -> np.ndarray:
        """M (N, C): per throw and channel the standardised mean residual (logged - replayed):
        trajectory channels sum(e) / (sigma sqrt(n)) over the throw's scored rows, the impact
        channels r / sqrt(var), the logged opening delay d / sd; 0 where a channel has no data.
        Under the null each entry has mean 0 (on the trajectory channels: up to the replay's
        systematic error, :attr:`bias_margin`); the bias test (:func:`noise.bias_tests`) uses their
        spread across throws, so correlated noise within a throw does not fool it."""
        M = np.zeros((len(self.throws), C))
        for n, (th, rep) in enumerate(zip(self.throws, reps)):
            L = rp.score_rows(th)
            e = np.concatenate([th.q[:L] - rep.meas_q[:L], th.qd[:L] - rep.meas_qd[:L]], axis=1)
            e = e[:, np.ravel(np.column_stack([np.arange(6), 6 + np.arange(6)]))]
            M[n, :N_TRAJ] = e.sum(axis=0) / (self.sig * np.sqrt(max(L, 1)))
            if (open_delay_s := th.open_delay_s) is not None:  # None without a logged opening
                d = open_delay_s - expected_logged_delay(rep.delay_mean_s, rep.delay_std_s)
                M[n, DELAY] = d / np.sqrt(max(rep.delay_std_s, 1e-3) ** 2 + TICK_S**2 / 12)
        r, v = impact_residuals(self.throws, reps)
        M[:, IMPACT] = r / np.sqrt(self.noise.impact_sigma_m**2 + v)
        return M


def expected_logged_delay(mean_s: float, std_s: float) -> float:
    """Expected logged opening delay (s) for a delay D = max(0, N(mean, std)): the payload is
    free at the first 10 ms row at or after command + D, so the logged delay is dt * ceil(D / dt)
    and its expectation dt * sum_j P(D > j dt) (smooth in mean and std; std floored at 1 ms)."""
    std = max(float(std_s), 1e-3)
    j = np.arange(0, int(np.ceil((mean_s + 8 * std) / TICK_S)) + 1)
    z = (j * TICK_S - mean_s) / (std * np.sqrt(2.0))
    return float(TICK_S * np.sum(0.5 * np.vectorize(math.erfc)(z)))


def estimate_noise(throws: list[LoggedThrow], nominal: list[Replay], sensors: dict | None = None) -> nz.NoiseModel:
    """Noise model from the nominal replay's residuals and the declared sensor spec (module
    doc of :mod:`noise`)."""
    sensors = sensors or {}
    sigma, source = {}, {}
    for c, kind, j in nz.TRAJ:
        ss, cnt = 0.0, 0
        for th, rep in zip(throws, nominal):
            L = rp.score_rows(th)
            e = (th.q[:L, j] - rep.meas_q[:L, j]) if kind == "q" else (th.qd[:L, j] - rep.meas_qd[:L, j])
            d2 = e[2:] - 2 * e[1:-1] + e[:-2]
            ss, cnt = ss + float(np.sum(d2 * d2)), cnt + d2.size
        s = float(np.sqrt(ss / (6.0 * cnt))) if cnt else 0.0
        fl = nz.floor_of(c)
        sigma[c], source[c] = (s, "measured") if s > fl else (fl, "floor")
    r, v = impact_residuals(throws, nominal)
    if sensors.get("impact_sigma_m") is not None:
        imp, source["impact"] = float(sensors["impact_sigma_m"]), "declared"
    else:
        scatter = float(np.mean(np.var(r, axis=0, ddof=1) - v.mean(axis=0))) if len(r) > 2 else 0.0
        imp, source["impact"] = max(np.sqrt(max(scatter, 0.0)), nz.MIN_IMPACT_SIGMA_M), "measured"
    return nz.NoiseModel(sigma, imp, source)
