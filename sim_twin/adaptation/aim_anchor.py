"""Anchor a twin-computed aim table to the site's own logged impacts.

Why: ``slinger diagnose`` fits a profile by REPLAYING the logged valve commands in the twin
(sim_twin.diagnosis.replay: the policy is not in that loop). Two effects that move the logged
impacts alike under the same valve commands need not move them alike in closed loop, where the
policy sees (and answers) one of them through its observation and not the other: a gripper IMU
latency changes what the policy observes, a cross wind or a grasp offset does not. So a fit
that names a different but replay-equivalent effect can give the aim correction (computed in
CLOSED loop under the fitted profile, sim_twin.adaptation.adapt) the wrong size or even the wrong sign.
Measured on heavy_load (earlier policy version, 2026-11-21): the fitted cabin drift predicted a bias of -0.06 to
-0.14 m in closed loop where the site's throws showed +0.21 to +0.37 m.

The logged throws themselves are closed-loop throws of the base policy on the site. For each
logged throw i (target distance d_i, measured downrange/crossrange error e_i) the twin's
closed-loop prediction under the fitted profile is the round-0 bias of the aim computation (the
unadapted base policy under the fitted profile) at d_i; the residual r_i = e_i - pred(d_i) is
what the fitted profile does not explain in closed loop. With a least-squares line r(a) (a
constant when the logged distances are too few or too close), the base policy aimed at a lands,
on the site, at ``a + B(a)`` with ``B(a) = b_fit(a) + r(a)``; b_fit is the twin's bias under the
fitted profile at aim a, sampled by every aim round (at aim d + offset: impact - aim = bias -
offset). The anchored table solves ``a + B(a) = d`` for every table distance d (bisection) and
stores ``a - d``. B is taken at the distance the policy is AIMED at, not at the target: a
site's bias grows with the throw's length (heavy_load, unadapted throw2d-robust-e, 20 throws
per target: +0.21 m at 7.5 m, +0.60 m at 10 m), and the policy asked for 9.5 m - 0.4 m throws
like a 9.1 m throw.

Error of the anchor: the residual's standard error is about sigma_throw / sqrt(N) for the
constant (30 logged throws of sigma 0.1-0.2 m: 0.02-0.04 m); the line is reported with its
standard error at every table distance's aim (``anchor.se_down_m``).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from runtime.throw_geometry import impact_errors

log = logging.getLogger(__name__)

MIN_THROWS = 8
"""Fewer matching logged throws than this: no anchor (the residual's error would be ~sigma/2)."""
MIN_SPAN_M = 1.0
"""The logged target distances must span at least this (and hold 3 distinct values) for a line;
else the residual is a constant."""


def logged_errors(dataset_dir: str | Path, policy_version: str, mode: str) -> dict:
    """Downrange / crossrange errors of the landed logged throws of ``policy_version``.

    Args:
        dataset_dir: a logged-throw dataset (sim_twin.diagnosis.dataset: ``index.json`` with
            target_m, impact_m (measured, machine frame, m), status, mode, policy_version).
        policy_version: only throws made by this version count (the anchor compares them with
            the twin's closed-loop bias of the same version).
        mode: "2d" or "3d".

    Returns:
        {"distance_m": (N,), "down_m": (N,), "cross_m": (N,), "skipped": {reason: count}}.

    Raises:
        FileNotFoundError: no index.json in ``dataset_dir``.
    """
    import json

    index = json.loads((Path(dataset_dir) / "index.json").read_text())
    d, down, cross = [], [], []
    skipped: dict[str, int] = {}
    for row in index.get("throws", []):
        why = ("not landed" if row.get("status") != "landed" else "no measured impact" if row.get("impact_m") is None
               else "other mode" if row.get("mode", mode) != mode else "other policy" if row.get("policy_version") != policy_version else None)
        if why:
            skipped[why] = skipped.get(why, 0) + 1
            continue
        e_down, e_cross = impact_errors(row["target_m"], row["impact_m"])
        d.append(math.hypot(*row["target_m"][:2]))
        down.append(e_down)
        cross.append(e_cross)
    return {"distance_m": np.array(d), "down_m": np.array(down), "cross_m": np.array(cross), "skipped": skipped}


def fit_residual(d: np.ndarray, r: np.ndarray) -> dict:
    """Least-squares line (or constant) of residuals ``r`` (N,) against distances ``d`` (N,), m.

    Returns:
        {"kind": "linear"|"constant", "coef": [c0, c1] (r = c0 + c1 (x - centre)), "centre_m",
        "cov": (2, 2) covariance of coef, "sigma_m": residual std, "n"}.

    Raises:
        ValueError: fewer than 2 points.
    """
    d, r = np.asarray(d, dtype=float), np.asarray(r, dtype=float)
    n = len(r)
    if n < 2:
        raise ValueError("need at least 2 logged throws to fit a residual")
    centre = float(d.mean())
    linear = len(np.unique(np.round(d, 3))) >= 3 and np.ptp(d) >= MIN_SPAN_M and n >= 2 * MIN_THROWS
    a = np.c_[np.ones(n), d - centre] if linear else np.ones((n, 1))
    coef, *_ = np.linalg.lstsq(a, r, rcond=None)
    dof = max(n - a.shape[1], 1)
    sigma = float(np.sqrt(np.sum((r - a @ coef) ** 2) / dof))
    cov = sigma**2 * np.linalg.inv(a.T @ a)
    if not linear:
        coef, cov = np.r_[coef, 0.0], np.diag([cov[0, 0], 0.0])
    return {"kind": "linear" if linear else "constant", "coef": coef.tolist(), "centre_m": centre, "cov": cov.tolist(),
            "sigma_m": sigma, "n": n}


def _eval(fit: dict, x) -> tuple[np.ndarray, np.ndarray]:
    """(value, standard error) of a fit_residual result at distances x."""
    x = np.atleast_1d(np.asarray(x, dtype=float)) - fit["centre_m"]
    a = np.c_[np.ones(len(x)), x]
    cov = np.asarray(fit["cov"])
    return a @ np.asarray(fit["coef"]), np.sqrt(np.einsum("ij,jk,ik->i", a, cov, a))


def _site_bias(history: list[dict], dist: np.ndarray, fit: dict):
    """B(a) (module doc): the twin's bias under the fitted profile at aim a, from every round's
    (aim, bias - offset) samples (linear interpolation, ends held), plus the residual line."""
    aims = np.concatenate([dist + np.asarray(h["downrange_offset_m"]) for h in history])
    b = np.concatenate([np.asarray(h["bias_m"]) - np.asarray(h["downrange_offset_m"]) for h in history])
    order = np.argsort(aims, kind="stable")
    aims, b = aims[order], b[order]
    uniq, inv = np.unique(np.round(aims, 6), return_inverse=True)
    b_mean = np.bincount(inv, weights=b) / np.bincount(inv)

    def bias(a):
        return np.interp(a, uniq, b_mean) + _eval(fit, a)[0]

    return bias


def _invert(d: float, bias, span_m: float = 3.0) -> float:
    """The aim a with a + bias(a) = d (bisection on [d - span, d + span]; the impact grows with
    the aim, as a throwing policy's does). Raises ValueError when no aim there reaches d."""
    lo, hi = d - span_m, d + span_m
    f = lambda a: a + float(bias(np.array([a]))[0]) - d  # noqa: E731
    if f(lo) > 0 or f(hi) < 0:
        raise ValueError(f"no aim within {span_m} m of {d} m reaches it under the anchored bias")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


def anchor_table(table: dict, history: list[dict], logged: dict, mode: str) -> tuple[dict, dict]:
    """The aim table corrected by the logged residual (module doc).

    Args:
        table: the aim block of sim_twin.adaptation.adapt.compute_aim_correction (distances_m,
            downrange_offset_m, crossrange_offset_m, ...).
        history: its rounds (offsets and measured bias per table distance); round 0 is the
            unadapted base policy under the fitted profile.
        logged: :func:`logged_errors` of the same base policy on the site.
        mode: "2d" (downrange only, as the aim rounds) or "3d" (also crossrange: the table's
            crossrange offset minus the crossrange residual at the target).

    Returns:
        (new table with an ``anchor`` entry, the anchor info: fits, residual per table
        distance and its standard error at the aim, throws used). With fewer than MIN_THROWS
        logged throws the table is returned unchanged and info["applied"] is False.

    Raises:
        ValueError: no aim reaches a table distance under the anchored bias.
    """
    n = len(logged["distance_m"])
    info = {"applied": False, "throws": n, "skipped": logged.get("skipped", {})}
    if n < MIN_THROWS:
        info["reason"] = f"{n} logged throws of the base policy (< {MIN_THROWS})"
        log.warning("aim anchor not applied: %s", info["reason"])
        return table, info
    dist = np.asarray(table["distances_m"], dtype=float)
    r0 = history[0]
    pred_down = np.interp(logged["distance_m"], dist, r0["bias_m"])
    pred_cross = np.interp(logged["distance_m"], dist, r0["mean_crossrange_m"])
    fit_down = fit_residual(logged["distance_m"], logged["down_m"] - pred_down)
    fit_cross = fit_residual(logged["distance_m"], logged["cross_m"] - pred_cross)
    bias = _site_bias(history, dist, fit_down)
    aims = np.array([_invert(float(x), bias) for x in dist])
    new_down = aims - dist
    r_down, se_down = _eval(fit_down, aims)
    cross = np.asarray(table["crossrange_offset_m"], dtype=float)
    r_cross, se_cross = _eval(fit_cross, dist)
    new_cross = cross - r_cross if mode == "3d" else cross
    info.update(applied=True, down_fit=fit_down, cross_fit=fit_cross, aims_m=aims.tolist(),
                residual_down_m=r_down.tolist(), se_down_m=se_down.tolist(),
                residual_cross_m=r_cross.tolist() if mode == "3d" else None, se_cross_m=se_cross.tolist() if mode == "3d" else None,
                logged_mean_down_m=float(np.mean(logged["down_m"])), predicted_mean_down_m=float(np.mean(pred_down)))
    log.info("aim anchored to %d logged throws: residual at the aims %s (%s), se %s", n,
             ", ".join(f"{x:g}: {v:+.3f}" for x, v in zip(dist, r_down)), fit_down["kind"],
             ", ".join(f"{v:.3f}" for v in se_down))
    new = {**table, "downrange_offset_m": [round(float(x), 4) for x in new_down],
           "crossrange_offset_m": [round(float(x), 4) for x in new_cross],
           "anchor": {"logged_throws": n, "kind": fit_down["kind"], "twin_downrange_offset_m": table["downrange_offset_m"],
                      "residual_down_m": [round(float(x), 4) for x in r_down], "se_down_m": [round(float(x), 4) for x in se_down]}}
    return new, info
