"""Fit every candidate effect on training throws and score it on held-out throws.

Per candidate (a library effect; its deterministic parameters, normalised to [0, 1] over the
prior range):

1. coarse start: the nominal value and a grid over the prior (5 points per parameter; 4 x 4 for
   two), all replayed in one batch; the best is the start;
2. bounded Levenberg-Marquardt on the residual vector of :func:`residuals.features`
   (:func:`mujoco.minimize.least_squares`, finite differences in one batched replay per
   iteration);
3. stochastic parameters (jitter, noise std) from residual spreads (Effect.estimate_spread);
4. uncertainty: cluster-robust (throws as clusters) sandwich covariance from the Jacobian at the
   optimum, 1 sigma in physical units;
5. held-out score: ``gain = 1 - J_test(fit) / J_test(nominal)``, penalised for the number of
   fitted parameters k over n held-out throws like an adjusted R^2:
   ``score = 1 - (1 - gain) (n - 1) / (n - k - 1)``.

Candidates are ranked by score. The best "explains" the gap when its score is at least
EXPLAINED_SCORE (most of the gap, held out); otherwise the answer is "unexplained".
"""

from __future__ import annotations

import io
import logging
import multiprocessing
import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from itertools import product

import mujoco.minimize as mjmin
import numpy as np

from sim_twin.diagnosis import replay as rp
from sim_twin.diagnosis import residuals as rs
from sim_twin.diagnosis.dataset import LoggedThrow
from sim_twin.effects import EFFECTS, Effect, EffectStack
from sim_twin.profile import RealityProfile

log = logging.getLogger(__name__)

EXPLAINED_SCORE = 0.5
"""A candidate explains the gap when its penalised held-out gain is at least this ("most")."""
MIN_GAP_J = 1.0
"""Below this nominal held-out J (residuals at their channel scales) there is no gap to explain."""
FD_EPS = 1e-4  # finite-difference step on normalised parameters


@dataclass
class CandidateFit:
    """Result for one candidate effect (parameters in physical units)."""

    effect: str
    params: dict[str, float]
    sigma: dict[str, float]
    k: int
    j_train_nominal: float
    j_train: float
    j_test_nominal: float
    j_test: float
    gain: float
    score: float
    iterations: int
    replays: int
    wall_s: float
    at_bound: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


class _Problem:
    """Residuals of one candidate over a throw set, vectorised over parameter columns."""

    def __init__(self, cls: type[Effect], throws: list[LoggedThrow], cache, base: RealityProfile):
        self.cls, self.throws, self.cache, self.base = cls, throws, cache, base
        self.det = [p for p in cls.params if not p.stochastic]
        self.lo = np.array([p.lo for p in self.det])
        self.hi = np.array([p.hi for p in self.det])
        self.calls = 0

    def theta(self, x: np.ndarray) -> dict[str, float]:
        v = self.lo + np.clip(x, 0.0, 1.0) * (self.hi - self.lo)
        return {p.name: float(val) for p, val in zip(self.det, v)}

    def x_of(self, values: dict[str, float]) -> np.ndarray:
        return np.array([(values[p.name] - p.lo) / (p.hi - p.lo) for p in self.det])

    def replays(self, X: np.ndarray, extra: dict | None = None) -> list[list[rp.Replay]]:
        stacks = [EffectStack([self.cls(**self.theta(X[:, j]), **(extra or {}))]) for j in range(X.shape[1])]
        self.calls += X.shape[1]
        return rp.replay(self.throws, stacks, self.base, dynamics_cache=self.cache)

    def residual(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        single = X.ndim == 1
        X = X[:, None] if single else X
        cols = [rs.features(self.throws, reps)[0] for reps in self.replays(X)]
        R = np.stack(cols, axis=1)
        return R[:, 0] if single else R

    def jacobian(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Finite-difference Jacobian (m, n), all columns in one batched replay."""
        x = np.asarray(x, dtype=float).reshape(-1)
        X = _fd_points(x)
        R = self.residual(X)
        return (R - np.asarray(r).reshape(-1, 1)) / (np.diag(X) - x)[None, :]


def _fd_points(x: np.ndarray) -> np.ndarray:
    """(n, n) forward-difference points (backward at the upper bound)."""
    n = x.size
    return x[:, None] + np.eye(n) * np.where(x + FD_EPS <= 1, FD_EPS, -FD_EPS)


def _grid(n: int) -> np.ndarray:
    pts = [0.05, 0.25, 0.5, 0.75, 0.95] if n == 1 else [0.1, 0.37, 0.63, 0.9]
    return np.array(list(product(pts, repeat=n))).T


def _sandwich(J: np.ndarray, r: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """Cluster-robust covariance (throws as clusters) of a least-squares estimate."""
    H = J.T @ J
    Hinv = np.linalg.pinv(H)
    meat = np.zeros_like(H)
    for c in np.unique(owner):  # -1 (dataset-level features) is one more cluster
        g = J[owner == c].T @ r[owner == c]
        meat += np.outer(g, g)
    return Hinv @ meat @ Hinv


def fit_candidate(cls: type[Effect], train, test, cache_train, cache_test, j0_train: float, j0_test: float, base: RealityProfile | None = None, max_iter: int = 25) -> CandidateFit:
    """Fit ``cls`` on ``train`` and score it on ``test`` (see module doc)."""
    t0 = time.time()
    base = base or RealityProfile()
    prob = _Problem(cls, train, cache_train, base)
    n = len(prob.det)
    nominal = {p.name: p.nominal for p in cls.params}
    x_nom = prob.x_of(nominal)
    G = np.concatenate([x_nom[:, None], _grid(n)], axis=1)
    R = prob.residual(G)
    x0 = G[:, int(np.argmin(np.sum(R * R, axis=0)))]
    out = io.StringIO()
    x, trace = mjmin.least_squares(x0, prob.residual, bounds=[np.zeros(n), np.ones(n)], jacobian=prob.jacobian, max_iter=max_iter,
                                   xtol=1e-5, gtol=1e-8, mu_factor=8.0, mu_max=1e5, verbose=0, output=out)
    # Jacobian and residual at the optimum (one batched replay), for the uncertainty
    X = np.concatenate([x[:, None], _fd_points(x)], axis=1)
    reps = prob.replays(X)
    f0, owner = rs.features(train, reps[0])
    Jac = np.stack([(rs.features(train, reps[j + 1])[0] - f0) / (X[j, j + 1] - x[j]) for j in range(n)], axis=1)
    cov = _sandwich(Jac, f0, owner) * np.outer(prob.hi - prob.lo, prob.hi - prob.lo)
    params = prob.theta(x)
    stoch = {}
    if hasattr(cls, "estimate_spread") and any(p.stochastic for p in cls.params):
        est = cls(**params).estimate_spread(rs.spreads(train, reps[0]))
        stoch = {p.name: float(np.clip(est[p.name], p.lo, p.hi)) for p in cls.params if p.stochastic and p.name in est}
    params.update(stoch)
    sigma = {p.name: float(np.sqrt(max(cov[i, i], 0.0))) for i, p in enumerate(prob.det)}
    test_prob = _Problem(cls, test, cache_test, base)
    test_reps = test_prob.replays(x[:, None], extra=stoch)[0]
    j_test = rs.gap(rs.features(test, test_reps)[0])
    j_train = rs.gap(f0)
    gain = 1.0 - j_test / j0_test if j0_test > 0 else 0.0
    n_test = len(test)
    score = 1.0 - (1.0 - gain) * (n_test - 1) / max(n_test - n - 1, 1)
    at_bound = [p.name for i, p in enumerate(prob.det) if x[i] < 1e-3 or x[i] > 1 - 1e-3]
    res = CandidateFit(cls.name, params, sigma, n, j0_train, j_train, j0_test, j_test, gain, score, len(trace), prob.calls + test_prob.calls, time.time() - t0, at_bound)
    log.info("candidate %-17s score %+.3f (held-out J %.3g -> %.3g) %s in %.1f s", cls.name, score, j0_test, j_test,
             {k: round(v, 4) for k, v in params.items()}, res.wall_s)
    return res


# --- all candidates, spread over processes -------------------------------------------------------
_W: dict = {}


def _init(train, test, base_dict):
    base = RealityProfile.from_dict(base_dict)
    _W.update(train=train, test=test, base=base)
    stacks = [EffectStack()]
    _W["cache_train"] = rp.simulate(train, stacks, base)[0]
    _W["cache_test"] = rp.simulate(test, stacks, base)[0]
    nominal_train = rp.replay(train, stacks, base, dynamics_cache=_W["cache_train"])[0]
    nominal_test = rp.replay(test, stacks, base, dynamics_cache=_W["cache_test"])[0]
    _W["j0_train"] = rs.gap(rs.features(train, nominal_train)[0])
    _W["j0_test"] = rs.gap(rs.features(test, nominal_test)[0])


def _fit_one(name: str) -> CandidateFit:
    w = _W
    return fit_candidate(EFFECTS[name], w["train"], w["test"], w["cache_train"], w["cache_test"], w["j0_train"], w["j0_test"], w["base"])


# dynamics candidates first: they are the slow ones, so the pool stays balanced
_ORDER = ("hanging_mass", "passive_friction", "valve_dead_band", "valve_delay", "valve_lag", "joint_rate_limit", "cabin_drift",
          "payload_drag", "grasp_offset", "release_delay", "imu_passive")


def fit_all(train: list[LoggedThrow], test: list[LoggedThrow], candidates: list[str] | None = None, base: RealityProfile | None = None, workers: int | None = None) -> list[CandidateFit]:
    """Fit and score every candidate; returns them ranked best first. Logs progress."""
    names = list(candidates or EFFECTS)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown candidate effects {unknown}; library: {sorted(EFFECTS)}")
    names.sort(key=lambda n: _ORDER.index(n) if n in _ORDER else len(_ORDER))
    base_dict = (base or RealityProfile()).to_dict()
    workers = max(1, min(workers or os.cpu_count() or 1, len(names)))
    results: list[CandidateFit] = []
    t0 = time.time()
    if workers == 1:
        _init(train, test, base_dict)
        for i, name in enumerate(names):
            results.append(_fit_one(name))
            log.info("diagnosis: %d/%d candidates fitted (%.0f s)", i + 1, len(names), time.time() - t0)
    else:
        # fork from a main thread (CLI, tests); spawn when called from a worker thread (the server),
        # where forking a process with other threads running is unsafe
        ctx = multiprocessing.get_context("fork" if threading.current_thread() is threading.main_thread() else "spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init, initargs=(train, test, base_dict)) as pool:
            for i, res in enumerate(pool.map(_fit_one, names)):
                results.append(res)
                log.info("diagnosis: %d/%d candidates fitted (%.0f s)", i + 1, len(names), time.time() - t0)
    return sorted(results, key=lambda r: -r.score)
