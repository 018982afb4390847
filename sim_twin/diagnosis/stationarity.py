"""Is the gap the same early and late in the log? A change-point test on per-throw series.

A diagnosis fits constant effects. A gap that changes during the log (a valve wearing in, a
sensor slipping, a payload swapped half-way) fitted as a constant is wrong twice: the fit is an
average that describes neither end, and a drift whose two halves cancel can even look like "no
gap". Every diagnosis (and the drift watch, :mod:`server.analysis.drift`) therefore tests each per-throw
series in throw order (the dataset's index order, the order the machine threw them) for a
change:

* **statistic**: the maximally selected two-sample t statistic over the split points k
  (at least MIN_SEGMENT throws on each side), T = max_k |mean(x[:k]) - mean(x[k:])| /
  (s_k sqrt(1/k + 1/(N - k))), s_k the pooled within-segment standard deviation (the
  likelihood-ratio test of one mean shift at an unknown point under normal errors; D. V. Hinkley,
  "Inference about the change-point in a sequence of random variables", Biometrika 57 (1970)
  1-17). It also has power against a gradual drift (a ramp splits best near its middle).
* **covariates**: the series is first regressed on the throw's covariates (the target
  distance, and a constant): a constant effect whose size depends on the distance (a release
  delay moves a far throw more than a near one) must not look like a drift when the targets
  change during the log. The test is on the regression's residuals.
* **p-value**: by permutation of the residuals over the throws (PERMUTATIONS draws, seeded),
  p = (1 + #{T_perm >= T}) / (1 + PERMUTATIONS): exact for exchangeable throws, with no normal
  or asymptotic approximation (the Brownian-bridge limit of the max-t is poor at 30 throws).
* **several series** (channels): Holm's step-down correction at family-wise ALPHA
  (:func:`test_series`), as the bias tests (:func:`noise.bias_tests`).

A series that changes is reported with where it changes (``change_at``: the index of the first
throw after the change), the means before and after, the step, and how fast: the slope per throw
of a straight line through the series (least squares, with its standard error), and which of
the two describes it better (``shape``: "step" or "ramp", the smaller residual sum of squares).
"""

from __future__ import annotations

import numpy as np

PERMUTATIONS = 3999
ALPHA = 0.01
"""Family-wise false-alarm probability of the change tests of one diagnosis (CHOSEN like
:data:`noise.BIAS_ALPHA`: one stationary dataset in a hundred shows a drift from noise alone)."""
MIN_SEGMENT = 5
"""Fewest throws on either side of a change point (a shorter end is too short to call a change)."""
MIN_THROWS = 2 * MIN_SEGMENT


def _max_t(X: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Max-t statistic of each row of X (R, N) over split points m..N-m, and its argmax k (R,)."""
    R, N = X.shape
    k = np.arange(m, N - m + 1)
    c1 = np.cumsum(X, axis=1)
    c2 = np.cumsum(X * X, axis=1)
    s1, q1 = c1[:, k - 1], c2[:, k - 1]
    s2, q2 = c1[:, -1:] - s1, c2[:, -1:] - q1
    n1, n2 = k.astype(float), (N - k).astype(float)
    m1, m2 = s1 / n1, s2 / n2
    ss = np.maximum((q1 - n1 * m1**2) + (q2 - n2 * m2**2), 0.0)
    sp = np.sqrt(ss / (N - 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.abs(m1 - m2) / (sp * np.sqrt(1.0 / n1 + 1.0 / n2))
    t = np.where(np.isfinite(t), t, 0.0)
    i = np.argmax(t, axis=1)
    return t[np.arange(R), i], k[i]


def change_point(x, covariates=None, permutations: int = PERMUTATIONS, seed: int = 0, min_segment: int = MIN_SEGMENT) -> dict:
    """Change test of one per-throw series in throw order (module doc).

    Args:
        x: (N,) values, throw order (any unit; the report keeps it).
        covariates: (N,) or (N, q) per-throw covariates regressed out first (e.g. the target
            distance), or None (a constant only).
        permutations: permutation draws for the p-value; seed: their seed.
        min_segment: fewest throws on either side of a change.

    Returns:
        {"n", "statistic": max-t, "p": permutation p, "change_at": index of the first throw after
        the best split, "mean_before", "mean_after", "step" (after - before, units of x),
        "slope_per_throw", "slope_se" (least-squares line through x), "shape": "step" | "ramp"};
        "p" is 1.0 and "change_at" None for a series too short (fewer than 2 min_segment throws)
        or without spread.

    Raises:
        ValueError: x not 1-D and finite, or covariates of another length.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError(f"change_point needs a finite 1-D series, got shape {x.shape}")
    N = len(x)
    out: dict[str, object] = {"n": N, "statistic": 0.0, "p": 1.0, "change_at": None, "mean_before": None, "mean_after": None, "step": 0.0,
           "slope_per_throw": 0.0, "slope_se": None, "shape": None}
    if N < 2 * min_segment or np.ptp(x) == 0.0:
        return out
    A = np.ones((N, 1))
    if covariates is not None:
        c = np.asarray(covariates, dtype=float)
        if c.ndim == 0 or c.shape[0] != N:
            raise ValueError(f"covariates must have one row per throw ({N}), got shape {c.shape}")
        c = c.reshape(N, -1)
        c = c[:, np.ptp(c, axis=0) > 0]  # a constant covariate adds nothing to the intercept
        A = np.hstack([A, c])
    beta, *_ = np.linalg.lstsq(A, x, rcond=None)
    r = x - A @ beta
    if np.ptp(r) <= 1e-12 * max(np.abs(x).max(), 1e-300):
        return out
    T, k = _max_t(r[None], min_segment)
    rng = np.random.default_rng(seed)
    P = np.argsort(rng.random((permutations, N)), axis=1)
    Tp, _ = _max_t(r[P], min_segment)
    kk = int(k[0])
    n = np.arange(N, dtype=float)
    slope, icpt = np.polyfit(n, x, 1)
    res_ramp = x - (icpt + slope * n)
    se = float(np.sqrt(res_ramp @ res_ramp / max(N - 2, 1) / np.sum((n - n.mean()) ** 2)))
    before, after = float(x[:kk].mean()), float(x[kk:].mean())
    res_step = np.concatenate([x[:kk] - before, x[kk:] - after])
    out.update(statistic=float(T[0]), p=float((1 + np.sum(Tp >= T[0])) / (1 + permutations)), change_at=kk,
               mean_before=before, mean_after=after, step=after - before, slope_per_throw=float(slope), slope_se=se,
               shape="step" if res_step @ res_step <= res_ramp @ res_ramp else "ramp")
    return out


def test_series(series: dict[str, np.ndarray], covariates=None, alpha: float = ALPHA, permutations: int = PERMUTATIONS,
                seed: int = 0) -> dict[str, dict]:
    """:func:`change_point` of every series, Holm-corrected over them at family-wise ``alpha``.

    Args:
        series: name -> (N,) series in throw order (all of one length N).
        covariates: as :func:`change_point` (shared by every series).

    Returns:
        name -> the change_point result plus "p_holm" and "drifting" (p_holm < alpha).
    """
    rows = {name: change_point(x, covariates, permutations, seed) for name, x in series.items()}
    order = sorted(rows, key=lambda n: rows[n]["p"])
    running = 0.0
    for i, name in enumerate(order):
        running = max(running, min(1.0, (len(order) - i) * rows[name]["p"]))
        rows[name]["p_holm"] = running
        rows[name]["drifting"] = bool(running < alpha)
    return rows


def split_halves(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(early, late) (n,) float throw weights: the first and the second half in throw order (the
    middle throw of an odd n in neither)."""
    h = n // 2
    early, late = np.zeros(n), np.zeros(n)
    early[:h] = 1.0
    late[n - h:] = 1.0
    return early, late


def describe(name: str, row: dict, throw_ids: list[str] | None = None, unit: str = "sigma") -> str:
    """One phrase for a drifting series: where, since which throw, how fast."""
    k = row["change_at"]
    since = f"throw {throw_ids[k]} (the {k + 1}th of {row['n']})" if throw_ids and k is not None else f"throw {k}"
    how = (f"a step of {row['step']:+.3g} {unit}" if row["shape"] == "step"
           else f"{row['slope_per_throw']:+.3g} {unit} per throw")
    return f"{name} changes since {since}: mean {row['mean_before']:+.3g} -> {row['mean_after']:+.3g} {unit} ({how}; p = {row['p_holm']:.2g})"
