"""Anchor a twin-computed aim table to the site's own logged impacts.

Why: ``slinger diagnose`` fits a profile by REPLAYING the logged valve commands in the twin
(sim_twin.diagnosis.replay: the policy is not in that loop). Two effects that move the logged
impacts alike under the same valve commands need not move them alike in closed loop, where the
policy sees (and answers) one of them through its observation and not the other: a gripper IMU
latency changes what the policy observes, a cross wind or a grasp offset does not. So a fit
that names a different but replay-equivalent effect can give the aim correction (computed in
CLOSED loop under the fitted profile, sim_twin.adapt) the wrong size or even the wrong sign.
Measured on heavy_load (session 2): the fitted cabin drift predicted a bias of -0.06 to
-0.14 m in closed loop where the site's throws showed +0.21 to +0.37 m.

The logged throws themselves are closed-loop throws of the base policy on the site. For each
logged throw i (target distance d_i, measured downrange/crossrange error e_i) the twin's
closed-loop prediction under the fitted profile is the round-0 bias of the aim computation (the
unadapted base policy under the fitted profile) at d_i; the residual r_i = e_i - pred(d_i) is
what the fitted profile does not explain in closed loop. A least-squares line r(d) (a constant
when the logged distances are too few or too close) is subtracted from the table:
``offset(d) -= r(d + offset(d)) / slope(d)``, r taken at the distance the policy is now aimed
at, slope = the measured d(bias)/d(aim) of the aim rounds (1 when not measured or outside 0.5-1.5).

Error of the anchor: the residual's standard error is about sigma_throw / sqrt(N) for the
constant (30 logged throws of sigma 0.1-0.2 m: 0.02-0.04 m); the line is reported with its
standard error at every table distance (``anchor.se_m``).
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
    d, down, cross, skipped = [], [], [], {}
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


def anchor_table(table: dict, history: list[dict], logged: dict, mode: str) -> tuple[dict, dict]:
    """The aim table corrected by the logged residual (module doc).

    Args:
        table: the aim block of sim_twin.adapt.compute_aim_correction (distances_m,
            downrange_offset_m, crossrange_offset_m, ...).
        history: its rounds; round 0 is the unadapted base policy under the fitted profile.
        logged: :func:`logged_errors` of the same base policy on the site.
        mode: "2d" (downrange only, as the aim rounds) or "3d" (also crossrange).

    Returns:
        (new table with an ``anchor`` entry, the anchor info: fits, residual per table
        distance and its standard error, throws used). With fewer than MIN_THROWS logged
        throws the table is returned unchanged and info["applied"] is False.
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
    down = np.asarray(table["downrange_offset_m"], dtype=float)
    cross = np.asarray(table["crossrange_offset_m"], dtype=float)
    slope = np.ones(len(dist))
    if len(history) >= 2:
        dd = np.asarray(history[-1]["downrange_offset_m"]) - np.asarray(history[-2]["downrange_offset_m"])
        moved = np.abs(dd) > 0.02
        s = np.where(moved, (np.asarray(history[-1]["bias_m"]) - np.asarray(history[-2]["bias_m"])) / np.where(moved, dd, 1.0), 1.0)
        slope = np.where((s > 0.5) & (s < 1.5), s, 1.0)
    r_down, se_down = _eval(fit_down, dist + down)
    new_down = down - r_down / slope
    r_cross, se_cross = _eval(fit_cross, dist)
    new_cross = cross - r_cross if mode == "3d" else cross
    info.update(applied=True, down_fit=fit_down, cross_fit=fit_cross, slope=slope.tolist(),
                residual_down_m=r_down.tolist(), se_down_m=se_down.tolist(),
                residual_cross_m=r_cross.tolist() if mode == "3d" else None, se_cross_m=se_cross.tolist() if mode == "3d" else None,
                logged_mean_down_m=float(np.mean(logged["down_m"])), predicted_mean_down_m=float(np.mean(pred_down)))
    log.info("aim anchored to %d logged throws: residual %s (%s), se %s", n,
             ", ".join(f"{x:g}: {v:+.3f}" for x, v in zip(dist, r_down)), fit_down["kind"],
             ", ".join(f"{v:.3f}" for v in se_down))
    new = {**table, "downrange_offset_m": [round(float(x), 4) for x in new_down],
           "crossrange_offset_m": [round(float(x), 4) for x in new_cross],
           "anchor": {"logged_throws": n, "kind": fit_down["kind"], "twin_downrange_offset_m": table["downrange_offset_m"],
                      "residual_down_m": [round(float(x), 4) for x in r_down], "se_down_m": [round(float(x), 4) for x in se_down]}}
    return new, info
