"""Replay logged throws in the twin: same initial state, same references, the runtime's
controller in the loop, a candidate set of effects on top of the nominal machine.

For every throw the replay starts from the logged state at swing start (valves neutral; the
machine is at rest there, so the active joints are the mean of the first REST_ROWS logged rows,
the velocities zero and the gripper hangs plumb; measurement effects' ``initial_state`` undoes
calibration offsets), feeds the logged valve commands (what the machine's valves actually got,
including the controller's reaction to sensor noise and to the effects; the runtime's
references are not needed) through the valve model and the effects'
setpoint and friction hooks, and steps MuJoCo at 100 Hz. Many throws and many effect
configurations run in one batch (the controller and valves vectorised over every pair; each
tick steps all pairs in one call of MuJoCo's ``mujoco.rollout`` from their states, with the
valve setpoints and the passive joints' friction as its controls: no Python loop over the
pairs, bit-identical to stepping one MjData per pair), which is what makes fitting affordable
on two cores. The valve chain (dead band, delay, lag, speed limit) does not depend on the
machine's state and is computed for all ticks before the stepping; a pair leaves the batch once
its throw's rows are done (the batch is ordered longest first). Configurations that reuse the
nominal joint motion (effects outside the dynamics) also reuse its measurement.

The payload part is computed from the replayed joint states afterwards: the grasp point while
held, the release at the logged opening row (``conditioned``: isolates flight from release
timing) and at the row the model's release delay predicts (``predicted``), and the flight
(analytic, or RK4 with the effects' flight acceleration) to the impact. Without a logged
opening the predicted impact is the expectation over the opening rows the model's delay
distribution gives (smooth in the delay: no 10 ms staircase), with its covariance.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout

from runtime.machine import JOINT_LOWER, JOINT_UPPER
from sim_twin.diagnosis.dataset import TICK_S, LoggedThrow
from sim_twin.twin.effects import Effect, EffectStack
from sim_twin.twin.effects.payload import grasp_point, integrate_flight
from sim_twin.twin.hydraulics import cylinder_step, dead_band_flow, lag_step
from sim_twin.twin.model import (
    PAYLOAD_RADIUS_M,
    load_model,
    passive_inertia,
    passive_inertia_of,
)
from sim_twin.twin.physics import (
    ballistic_impact_time,
    passive_friction_force,
)
from sim_twin.twin.profile import RealityProfile

log = logging.getLogger(__name__)

MAX_RELEASE_DELAY_S = 0.8  # nominal-dynamics replays run at least this long after the release command
SCORE_ROWS_AFTER_CMD = 40  # joint channels are compared up to 0.4 s after the release command
REST_ROWS = 4  # first logged rows averaged for the start state (valve delay >= 40 ms: nothing moves yet)
MIN_JITTER_S = 0.002  # floor of the opening-delay spread in the expected impact (keeps it smooth)
FLIGHT_DT_S = 0.02
"""RK4 step of the replay's flights under drag or wind (the simulated machine uses 5 ms). Measured
against 5 ms on 50 random flights at the priors' extremes (wind 15 m/s on both axes, drag
coefficient 1.5): the impact moves by at most 0.75 mm, against 5 cm impact noise; 4x fewer steps
(sim_twin.preview.preview's Monte Carlo uses the same step)."""


_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED


@dataclass
class Replay:
    """One throw replayed under one effect configuration.

    Attributes:
        q, qd: (R, 6) true replayed states on the replay rows (R >= logged rows).
        meas_q, meas_qd: (R, 6) what the sensors would have given (measurement effects).
        held_pos_m: (T_open, 3) grasp point on the logged rows before the logged opening ((0, 3)
            when the log has no payload tracking).
        delay_mean_s / delay_std_s: the model's release delay.
        cond: flight released at the logged opening row: dict(pos_m (F, 3) at the logged
            payload times, impact_m (3,), impact_t_s, open_row); without a logged opening the
            same as pred.
        pred: released where the model's delay puts it: impact_m is the expectation over the
            opening rows, impact_cov_m2 (2, 2) its covariance in x, y (release jitter); pos_m
            from the most likely row.
    """

    q: np.ndarray
    qd: np.ndarray
    meas_q: np.ndarray
    meas_qd: np.ndarray
    held_pos_m: np.ndarray
    delay_mean_s: float
    delay_std_s: float
    cond: dict
    pred: dict


def start_state(th: LoggedThrow, stack: EffectStack) -> tuple[np.ndarray, np.ndarray]:
    """(q (6,), qd (6,)) true state at swing start (see module doc)."""
    q = th.q[:REST_ROWS].mean(axis=0)
    q, _ = stack.initial_state(q, np.zeros(6))
    q = np.array(q, dtype=float)
    q[4], q[5] = -(q[1] + q[2]), 0.0
    return q, np.zeros(6)


def score_rows(th: LoggedThrow) -> int:
    """Logged rows whose joint channels the diagnosis compares."""
    return min(len(th.t_s), th.cmd_row + SCORE_ROWS_AFTER_CMD)


def replay_rows(th: LoggedThrow, delay_s: float = MAX_RELEASE_DELAY_S) -> int:
    """Rows to replay: the compared ones, extended (valves neutral after the log ends) to cover
    an opening ``delay_s`` after the command."""
    return max(score_rows(th), th.cmd_row + int(np.ceil(delay_s / TICK_S)) + 2)


@lru_cache(maxsize=1)
def _base_model() -> mujoco.MjModel:
    return load_model()


class _Column:
    """Static per-configuration quantities."""

    def __init__(self, stack: EffectStack, base: RealityProfile):
        self.stack = stack
        self.measure_stack = EffectStack(base.sensing.effects() + list(stack.effects))  # the machine's sensing first
        if stack.has("model"):
            self.model = copy.copy(_base_model())
            stack.model(self.model)
            self.inertia = passive_inertia_of(self.model)
        else:  # shared, never written (MuJoCo's rollout only reads it)
            self.model = _base_model()
            self.inertia = passive_inertia()
        self.hyd = stack.hydraulics(base.hydraulics)
        self.viscous, self.coulomb = stack.passive_friction(base.passive_viscous_per_s, base.passive_coulomb_rad_per_s2)
        self.delay_mean_s, self.delay_std_s = stack.release_delay(base.release_delay_mean_s, base.release_delay_std_s)
        self.offset = stack.grasp_offset()
        self.flight = stack.flight_accel if stack.has("flight_accel") else None
        self.setpoint = stack.has("setpoint")
        self.measure_impact = stack.measure_impact if stack.has("measure_impact") else None


def simulate(throws: list[LoggedThrow], stacks: list[EffectStack], base: RealityProfile | None = None,
             long: bool = False) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Batched dynamic replay.

    Args:
        throws: N logged throws.
        long: replay far enough for any opening delay up to MAX_RELEASE_DELAY_S (a cache for
            release-stage candidates), else just past the stacks' own delays.
        stacks: K effect configurations (on top of ``base``, default the nominal profile).

    Returns:
        [k][n] -> (q (R_n, 6), qd (R_n, 6)) true replayed states, row 0 = logged swing start.
    """
    base = base or RealityProfile()
    cols = [_Column(s, base) for s in stacks]
    N, K = len(throws), len(cols)
    M = N * K
    longest = max(MAX_RELEASE_DELAY_S if long else c.delay_mean_s + 5 * max(c.delay_std_s, MIN_JITTER_S) for c in cols)
    rows = np.array([replay_rows(th, longest) for th in throws])
    T = int(rows.max())
    logged_u = np.zeros((N, T, 4))
    for n, th in enumerate(throws):
        L = min(len(th.t_s), T)
        logged_u[n, :L] = th.valve_u[:L]
    # pairs (configuration, throw), longest replay first: a pair leaves the batch once its own
    # rows are done, so the active pairs are always a prefix (each pair's stepping is
    # independent of the others': the same numbers as stepping the whole batch to the longest)
    pair_rows = np.tile(rows, K)
    order = np.argsort(-pair_rows, kind="stable")
    sys_col = np.repeat(np.arange(K), N)[order]
    sys_thr = np.tile(np.arange(N), K)[order]
    pair_rows = pair_rows[order]
    models = [cols[sys_col[i]].model for i in range(M)]
    nq, nv, nu = models[0].nq, models[0].nv, models[0].nu
    state = np.zeros((M, mujoco.mj_stateSize(models[0], _STATE)))  # time, qpos, qvel (the model has no activations)
    state[:, 1:1 + nq] = [start_state(throws[sys_thr[i]], cols[sys_col[i]].stack)[0] for i in range(M)]
    control = np.zeros((M, 1, nu + nv))  # ctrl, then qfrc_applied (mjtState bit order)
    stepped = np.zeros((M, 1, state.shape[1]))
    work = [mujoco.MjData(models[0])]  # rollout's scratch data (one thread: the sweeps run in processes already)
    def per(f):
        return np.stack([f(cols[c]) for c in sys_col])

    db = per(lambda c: c.hyd.dead_band)
    steps = np.round(per(lambda c: c.hyd.delay_s) / TICK_S, 9)
    i0 = np.floor(steps).astype(int)
    frac = steps - i0
    lag = per(lambda c: c.hyd.lag_s)
    vmax = per(lambda c: c.hyd.velocity_limit)
    visc = per(lambda c: np.full(2, c.viscous))
    coul = per(lambda c: np.full(2, c.coulomb))
    inertia = per(lambda c: c.inertia)
    db, i0, frac, lag, vmax = (np.broadcast_to(a, (M, 4)) for a in (db, i0, frac, lag, vmax))
    # the valve chain (dead band, transport delay, lag, speed limit) does not depend on the
    # machine's state: computed for every tick at once (the lag's recursion tick by tick), the
    # same operations on the same numbers as one tick at a time
    pair_idx, valve_idx = np.arange(M)[:, None], np.arange(4)[None, :]
    flow = dead_band_flow(np, np.clip(logged_u[sys_thr, : T - 1].transpose(1, 0, 2), -1.0, 1.0), db)  # (T - 1, M, 4)
    Lb = int(i0.max()) + 1
    flow = np.concatenate([np.zeros((Lb, M, 4)), flow])  # zero flow before the log starts
    ticks = Lb + np.arange(T - 1)[:, None, None]
    delayed = flow[ticks - i0, pair_idx, valve_idx]
    if np.any(frac > 0):
        delayed = np.where(frac > 0, (1 - frac) * delayed + frac * flow[ticks - i0 - 1, pair_idx, valve_idx], delayed)
    lagged = np.zeros((T, M, 4))
    for t in range(T - 1):
        lagged[t + 1] = lag_step(lagged[t], delayed[t], lag, TICK_S)
    sp_all = np.clip(lagged[1:] * vmax, -vmax, vmax)  # (T - 1, M, 4) the valves' joint velocities
    Q = state[:, 1:1 + nq].copy()
    QD = state[:, 1 + nq:1 + nq + nv].copy()
    outq = np.zeros((M, T, 6))
    outqd = np.zeros((M, T, 6))
    outq[:, 0], outqd[:, 0] = Q, QD
    lo, hi = JOINT_LOWER[:4], JOINT_UPPER[:4]
    x_ref = np.clip(Q[:, :4], lo, hi)  # the cylinders' oil columns (SimulatedMachine.reset)
    sp_cols = [(k, np.flatnonzero(sys_col == k)) for k in range(K) if cols[k].setpoint]
    for t in range(T - 1):
        m = int(np.count_nonzero(pair_rows > t + 1))  # pairs that still need row t + 1
        sp = sp_all[t, :m]
        if sp_cols:
            sp = sp.copy()
            for k, sel in sp_cols:
                sel = sel[sel < m]
                if len(sel):
                    sp[sel] = cols[k].stack.setpoint(sp[sel], Q[sel], QD[sel])
        x_ref[:m], sp = cylinder_step(np, x_ref[:m], sp, Q[:m, :4], lo, hi, TICK_S)
        control[:m, 0, :nu] = sp
        control[:m, 0, nu + 4:nu + 6] = passive_friction_force(np, QD[:m, 4:6], inertia[:m], visc[:m], coul[:m])
        rollout.rollout(models[:m], work, state[:m], control[:m], control_spec=_CONTROL, skip_checks=True, nstep=1, state=stepped[:m])
        state[:m] = stepped[:m, 0]
        Q = state[:, 1:1 + nq]
        QD = state[:, 1 + nq:1 + nq + nv]
        outq[:m, t + 1], outqd[:m, t + 1] = Q[:m], QD[:m]
    res: list[list[Any]] = [[None] * N for _ in range(K)]  # every entry is set below
    for i in range(M):
        n = sys_thr[i]
        res[sys_col[i]][n] = (outq[i, : rows[n]], outqd[i, : rows[n]])
    return res


def _measure(stack: EffectStack, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free measurement of a whole trajectory (R, 6) through the stack's measure hooks.

    The hooks get the history (H, R, 6) with row h the state h rows earlier (the first row
    before the start): a read-only strided view of the trajectory padded with its first row
    (no gathered copy; :meth:`EffectStack.measure` copies it before any effect sees it)."""
    if not stack.has("measure"):
        return q, qd
    H = stack.history_steps()
    return stack.measure(_history(q, H), _history(qd, H), TICK_S, None)


def _history(x: np.ndarray, H: int) -> np.ndarray:
    """(H, R, k) read-only view: [h, r] = x[max(r - h, 0)] for x (R, k)."""
    xp = np.concatenate([np.repeat(x[:1], H - 1, axis=0), x]) if H > 1 else np.ascontiguousarray(x)
    s0, s1 = xp.strides
    return np.lib.stride_tricks.as_strided(xp[H - 1:], shape=(H,) + x.shape, strides=(-s0, s0, s1), writeable=False)


def effect_key(effect: Effect) -> tuple:
    """Hashable identity of an effect: its class and its parameter values, exactly (floats by
    their bits, arrays by dtype, shape and bytes, other values by type and value or repr)."""
    def exact(v):
        if isinstance(v, np.ndarray):
            return (v.dtype.str, v.shape, v.tobytes())
        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, (list, tuple)):
            return tuple(exact(x) for x in v)
        if isinstance(v, float):
            return ("float", v.hex())  # -0.0 apart from 0.0
        return (type(v).__name__, v) if isinstance(v, (int, str, bool, type(None))) else ("repr", repr(v))

    return (type(effect),) + tuple((k, exact(v)) for k, v in sorted(effect.values.items()))


_MEASURED: dict[tuple, tuple] = {}
"""Measurements of shared joint motion (:func:`_measure_shared`): key -> (q, qd, meas_q, meas_qd)."""
_MEASURED_MAX = 512


def _measure_shared(stack: EffectStack, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_measure` of joint motion that many configurations share (the dynamics cache): the
    measurement depends only on the trajectory and the stack's measuring effects (and its history
    length), so configurations whose other effects act elsewhere (release, payload, flight,
    impact sensing) reuse it. Keyed on the arrays' identity (the entry keeps them alive)."""
    fx = tuple(effect_key(e) for e in stack.effects if type(e).measure is not Effect.measure)
    key = (id(q), id(qd), stack.history_steps(), fx)
    hit = _MEASURED.get(key)
    if hit is not None and hit[0] is q and hit[1] is qd:
        return hit[2], hit[3]
    mq, mqd = _measure(stack, q, qd)
    if len(_MEASURED) >= _MEASURED_MAX:
        oldest = next(iter(_MEASURED), None)
        if oldest is not None:
            _MEASURED.pop(oldest, None)  # another thread may have taken it
    _MEASURED[key] = (q, qd, mq, mqd)
    return mq, mqd


def open_row(th: LoggedThrow, delay_s: float) -> int:
    """Row at which the payload is free for a deterministic delay (SimulatedMachine.step: the
    first step at or after command + delay)."""
    return th.cmd_row + int(np.ceil(max(delay_s, 0.0) / TICK_S - 1e-9))


def _fly(col: _Column, q: np.ndarray, qd: np.ndarray) -> dict:
    """Flights of a batch of release states q, qd (B, 6) under the configuration: dict(p0, v0
    (B, 3) release position and velocity, t_hit (B,) flight time, hit (B, 3) landing spot with
    z = 0, ts (S,) / ps (S, B, 3) the integrated trajectory, None when analytic)."""
    p0, v0 = grasp_point(q, qd, col.offset)
    if col.flight is None:
        t_hit = ballistic_impact_time(np, p0.T, v0.T, PAYLOAD_RADIUS_M)
        hit = p0 + v0 * t_hit[:, None] + 0.5 * np.array([0.0, 0.0, -9.81]) * t_hit[:, None] ** 2
        ts = ps = None
    else:
        ts, ps, _, t_hit, hit = integrate_flight(p0, v0, col.flight, dt_s=FLIGHT_DT_S)
    hit = np.array(hit, dtype=float)
    hit[:, 2] = 0.0
    return {"p0": p0, "v0": v0, "t_hit": t_hit, "hit": hit, "ts": ts, "ps": ps}


def _flight_of(th: LoggedThrow, fl: dict, i: int, row: int) -> dict:
    """Entry i of a :func:`_fly` batch, released at ``row`` of throw ``th``: dict(pos_m (F, 3)
    at the logged payload times, impact_m (3,), impact_t_s, open_row)."""
    t_open = row * TICK_S
    p0, v0, t_hit, ts, ps = fl["p0"], fl["v0"], fl["t_hit"], fl["ts"], fl["ps"]
    tt = np.clip(th.payload_t_s - t_open, 0.0, t_hit[i])
    if not len(tt):  # no payload tracking logged (a real machine's log): nothing to compare
        pos = np.zeros((0, 3))
    elif ps is None:
        pos = p0[i] + v0[i] * tt[:, None] + 0.5 * np.array([0.0, 0.0, -9.81]) * tt[:, None] ** 2
    else:
        assert ts is not None  # integrated flights come with their times
        pos = np.stack([np.interp(tt, ts, ps[:, i, j]) for j in range(3)], axis=-1)
    return {"pos_m": pos, "impact_m": fl["hit"][i].copy(), "impact_t_s": t_open + float(t_hit[i]), "open_row": row}


def _flights(throws: list[LoggedThrow], col: _Column, trajs, rows: list[int]) -> list[dict]:
    """Flights of all throws of one configuration, released at ``rows`` (batched integration)."""
    rows = [min(r, len(trajs[n][0]) - 1) for n, r in enumerate(rows)]
    q = np.stack([trajs[n][0][r] for n, r in enumerate(rows)])
    qd = np.stack([trajs[n][1][r] for n, r in enumerate(rows)])
    fl = _fly(col, q, qd)
    return [_flight_of(th, fl, n, rows[n]) for n, th in enumerate(throws)]


def _open_distribution(mean_s: float, std_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(row offsets j (J,), probabilities (J,)) of the opening row cmd_row + j for a delay
    D = max(0, N(mean, std)): j = ceil(D / dt) (see :func:`open_row`)."""
    std = max(float(std_s), MIN_JITTER_S)
    j = np.arange(max(0, int(np.floor((mean_s - 5 * std) / TICK_S))), int(np.ceil((mean_s + 5 * std) / TICK_S)) + 2)
    cdf = 0.5 * (1.0 + np.vectorize(math.erf)((j * TICK_S - mean_s) / (std * math.sqrt(2.0))))
    p = np.diff(np.concatenate([[0.0], cdf]))
    keep = p > 1e-6
    return j[keep], p[keep] / p[keep].sum()


def finish(throws: list[LoggedThrow], col: _Column, trajs, shared: bool = False) -> list[Replay]:
    """Measurement, held payload and flights for the dynamic replays ``trajs`` ([n] -> (q, qd)).
    ``shared``: ``trajs`` is joint motion other configurations reuse (the dynamics cache): its
    measurements are kept for them (:func:`_measure_shared`)."""
    offs, probs = _open_distribution(col.delay_mean_s, col.delay_std_s)
    J, N = len(offs), len(throws)
    likely = int(np.argmax(probs))
    # every throw released at every opening row (batch entry k * N + n: offset k, throw n)
    rows = np.stack([np.minimum(th.cmd_row + offs.astype(int), len(trajs[n][0]) - 1) for n, th in enumerate(throws)])  # (N, J)
    q = np.stack([trajs[n][0][rows[n]] for n in range(N)]).transpose(1, 0, 2).reshape(J * N, -1)
    qd = np.stack([trajs[n][1][rows[n]] for n in range(N)]).transpose(1, 0, 2).reshape(J * N, -1)
    fl = _fly(col, q, qd)
    hits = fl["hit"].reshape(J, N, 3)
    pred = []
    for n, th in enumerate(throws):
        h = np.ascontiguousarray(hits[:, n])
        mean = probs @ h
        dev = h[:, :2] - mean[:2]
        pred.append({**_flight_of(th, fl, likely * N + n, int(rows[n, likely])), "impact_m": mean, "impact_cov_m2": (dev * probs[:, None]).T @ dev})
    logged = [n for n, th in enumerate(throws) if th.open_row is not None]
    cond = list(pred)
    if logged:
        for n, f in zip(logged, _flights([throws[n] for n in logged], col, [trajs[n] for n in logged], [int(throws[n].open_row or 0) for n in logged])):
            cond[n] = {**f, "impact_cov_m2": np.zeros((2, 2))}
    if col.measure_impact is not None:  # what the impact sensor reads (the covariance is unchanged by a bias)
        pred = [{**f, "impact_m": col.measure_impact(f["impact_m"])} for f in pred]
        cond = [pred[n] if th.open_row is None else {**cond[n], "impact_m": col.measure_impact(cond[n]["impact_m"])} for n, th in enumerate(throws)]
    out = []
    for n, th in enumerate(throws):
        q, qd = trajs[n]
        mq, mqd = (_measure_shared if shared else _measure)(col.measure_stack, q, qd)
        n_held = th.open_row if th.open_row is not None else th.cmd_row
        held = grasp_point(q[:n_held], qd[:n_held], col.offset)[0] if len(th.payload_t_s) else np.zeros((0, 3))
        out.append(Replay(q=q, qd=qd, meas_q=mq, meas_qd=mqd, held_pos_m=held, delay_mean_s=col.delay_mean_s,
                          delay_std_s=col.delay_std_s, cond=cond[n], pred=pred[n]))
    return out


def needs_dynamics(stack: EffectStack) -> bool:
    """Whether the stack changes the joint motion (dynamics effects, or a changed start state)."""
    return any(e.stage == "dynamics" for e in stack.effects) or any(stack.has(h) for h in ("initial_state", "hydraulics", "setpoint", "passive_friction", "model"))


def replay_on(throws: list[LoggedThrow], stack: EffectStack, trajs: list, base: RealityProfile | None = None) -> list[Replay]:
    """Replays of ``throws`` under ``stack`` on given joint motion ``trajs`` ([n] -> (q, qd), a
    ``simulate(..., long=True)`` result of a stack with the same dynamics: the caller vouches
    that ``stack``'s other effects act outside the dynamics)."""
    return finish(throws, _Column(stack, base or RealityProfile()), trajs, shared=True)


def replay(throws: list[LoggedThrow], stacks: list[EffectStack], base: RealityProfile | None = None, dynamics_cache: list | None = None) -> list[list[Replay]]:
    """Replay ``throws`` under each stack; returns [k][n] Replays.

    Args:
        dynamics_cache: the nominal ``simulate`` result for these throws ([n] -> (q, qd)); used
            for stacks whose effects all act outside the dynamics (release, payload, flight,
            measurement), which then cost no MuJoCo stepping.
    """
    base = base or RealityProfile()
    dyn_idx = [k for k, s in enumerate(stacks) if dynamics_cache is None or needs_dynamics(s)]
    sims = simulate(throws, [stacks[k] for k in dyn_idx], base) if dyn_idx else []
    out = []
    for k, stack in enumerate(stacks):
        col = _Column(stack, base)
        traj = sims[dyn_idx.index(k)] if k in dyn_idx else dynamics_cache
        out.append(finish(throws, col, traj, shared=k not in dyn_idx))
    return out
