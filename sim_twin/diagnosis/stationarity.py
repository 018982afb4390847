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
* **several series** (the channels of one diagnosis): one test of them together
  (:func:`combined_change`): the largest, over the split points, of the sum over the channels
  of t^2 at that split, its p by permuting the throws in every channel alike. A change of the
  machine moves the gap, at one throw, in the channels that carry it, and their evidence adds up
  there. Each channel is also tested on its own (:func:`change_point`, Holm over the channels,
  :func:`test_series`): those rows say where and how a change goes, but do not decide it.
* **the decision**: a diagnosis tests its nominal residuals and, when it names effects, the
  residuals they leave; :func:`verdict.drift_of` calls the log drifting where a combined test
  passes Holm's correction over the two at family-wise ALPHA (or the named effects' fits on the
  two halves disagree, :func:`forward.split_fits`).

Why one combined test decides, not the smallest of the per-channel p: throws of one log are
exchangeable when nothing changes, also under an effect the twin does not model. That effect's
misfit makes the per-throw residuals large, heavy-tailed and dependent on each throw's target
and pose, but not on its place in the log, so the permutation test stays exact there; what no
test avoids is its false-alarm rate. With 14 channels before and 14 after the fit, one series of
28 crossing a per-series bar alone is what chance does (about once in a hundred logs at Holm
0.01 per set of 14), and a drifting answer replaces every other answer. The combined test puts
that channel's evidence beside the others' at the same throw.

A log that changes is reported with where it changes (``change_at``: the index of the first
throw after the change), the channels that change there, their means before and after, the step,
and how fast: the slope per throw of a straight line through the series (least squares, with its
standard error), and which of the two describes it better (``shape``: "step" or "ramp", the
smaller residual sum of squares).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

PERMUTATIONS = 3999
ALPHA = 0.001
"""Family-wise false-alarm probability of the drift decision of one diagnosis: Holm over its
combined tests (the nominal residuals, and those the named effects leave) (CHOSEN: a "drifting"
answer replaces every other answer and sends the site looking for what changed, so one
stationary log in a thousand may be called drifting by chance; the 100-case diagnosis benchmark,
94 of whose cases are stationary, then expects 0.1 such answers). The smallest p of PERMUTATIONS
draws, 1/4000, passes it among two tests. The benchmark's drifting cases give combined p at or
near that floor; its stationary case 38 (a constant hose spring on the 3D machine, an effect the
twin does not model), called drifting by one channel's own test, gives 0.07 and 0.25."""
COMBINED = "channels together"
"""Key of a family's :func:`combined_change` row beside its channels' rows (:func:`test_series`)."""
CHANGE_T = 3.0
"""A channel takes part in a combined change when its own |t| at the common split is at least
this (CHOSEN: the two-sided 0.3 % point of a normal; the largest is named where none is)."""
MIN_SEGMENT = 5
"""Fewest throws on either side of a change point (a shorter end is too short to call a change)."""
MIN_THROWS = 2 * MIN_SEGMENT


def _t_splits(X: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """|two-sample t| of each row of X (R, N) at every split point k = m..N-m: (R, K), and k (K,)."""
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
    return np.where(np.isfinite(t), t, 0.0), k


def _max_t(X: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Max-t statistic of each row of X (R, N) over split points m..N-m, and its argmax k (R,)."""
    t, k = _t_splits(X, m)
    i = np.argmax(t, axis=1)
    return t[np.arange(len(t)), i], k[i]


def _sum_t2(X: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Combined statistic of C series under R orderings, X (C, R, N): the largest, over the split
    points, of the sum over the series of t^2 at that split (R,), and its argmax k (R,)."""
    C, R, N = X.shape
    t, k = _t_splits(X.reshape(C * R, N), m)
    s2 = (t.reshape(C, R, -1) ** 2).sum(axis=0)
    i = np.argmax(s2, axis=1)
    return s2[np.arange(R), i], k[i]


def _residuals(x: np.ndarray, covariates) -> np.ndarray:
    """x (N,) less its least-squares fit on a constant and the covariates ((N,) or (N, q), or None).

    Raises:
        ValueError: covariates of another length than x.
    """
    N = len(x)
    A = np.ones((N, 1))
    if covariates is not None:
        c = np.asarray(covariates, dtype=float)
        if c.ndim == 0 or c.shape[0] != N:
            raise ValueError(f"covariates must have one row per throw ({N}), got shape {c.shape}")
        c = c.reshape(N, -1)
        c = c[:, np.ptp(c, axis=0) > 0]  # a constant covariate adds nothing to the intercept
        A = np.hstack([A, c])
    beta, *_ = np.linalg.lstsq(A, x, rcond=None)
    return x - A @ beta


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
    r = _residuals(x, covariates)
    if np.ptp(r) <= 1e-12 * max(np.abs(x).max(), 1e-300):
        return out
    T, k = _max_t(r[None], min_segment)
    rng = np.random.default_rng(seed)
    P = np.argsort(rng.random((permutations, N)), axis=1)
    Tp, _ = _max_t(r[P], min_segment)
    kk = int(k[0])
    out.update(statistic=float(T[0]), p=float((1 + np.sum(Tp >= T[0])) / (1 + permutations)), **_shape(x, kk))
    return out


def _shape(x: np.ndarray, kk: int) -> dict:
    """change_at, means before / after the split kk, step, the least-squares line and the shape."""
    N = len(x)
    n = np.arange(N, dtype=float)
    slope, icpt = np.polyfit(n, x, 1)
    res_ramp = x - (icpt + slope * n)
    se = float(np.sqrt(res_ramp @ res_ramp / max(N - 2, 1) / np.sum((n - n.mean()) ** 2)))
    before, after = float(x[:kk].mean()), float(x[kk:].mean())
    res_step = np.concatenate([x[:kk] - before, x[kk:] - after])
    return {"change_at": kk, "mean_before": before, "mean_after": after, "step": after - before, "slope_per_throw": float(slope),
            "slope_se": se, "shape": "step" if res_step @ res_step <= res_ramp @ res_ramp else "ramp"}


def combined_change(series: dict[str, np.ndarray], covariates=None, permutations: int = PERMUTATIONS, seed: int = 0,
                    min_segment: int = MIN_SEGMENT) -> dict | None:
    """One change test of several series together: do they change at one throw? (module doc)

    The statistic is the largest, over the split points k, of the sum over the series of the
    squared two-sample t at k (each series' residuals after the covariates, as
    :func:`change_point`); its p by permuting the throws, the same permutation in every series
    (exact for exchangeable throws, whatever the series' correlation with each other). With one
    series it is :func:`change_point`'s test.

    Args:
        series: name -> (N,) series in throw order (all of one length N).
        covariates: as :func:`change_point`; permutations, seed: the permutation draws.

    Returns:
        {"n", "series": the names tested, "statistic", "p", "change_at": index of the first throw
        after the best common split, "channels": the series whose |t| there is at least CHANGE_T
        (the largest alone where none is), largest first, "t": {name: |t| at that split},
        "shapes": {channel: means before / after that split, step, slope, shape (as
        :func:`change_point`)}}, or
        None where no series is usable (too short, or without spread after the covariates).

    Raises:
        ValueError: a series not 1-D and finite, or covariates of another length.
    """
    names, R = [], []
    for name, x in series.items():
        x = np.asarray(x, dtype=float)
        if x.ndim != 1 or not np.all(np.isfinite(x)):
            raise ValueError(f"combined_change needs finite 1-D series, got shape {x.shape} for {name}")
        if len(x) < 2 * min_segment or np.ptp(x) == 0.0:
            continue
        r = _residuals(x, covariates)
        if np.ptp(r) <= 1e-12 * max(np.abs(x).max(), 1e-300):
            continue
        names.append(name)
        R.append(r)
    if not R:
        return None
    X = np.array(R)
    C, N = X.shape
    S, k = _sum_t2(X[:, None, :], min_segment)
    rng = np.random.default_rng([seed, 2])
    hits, done, chunk = 0, 0, max(20000 // C, 200)
    while done < permutations:  # chunked: C x chunk x N values at a time
        n = min(chunk, permutations - done)
        Sp, _ = _sum_t2(X[:, np.argsort(rng.random((n, N)), axis=1)], min_segment)
        hits += int(np.sum(Sp >= S[0]))
        done += n
    kk = int(k[0])
    t_all, ks = _t_splits(X, min_segment)
    t_k = {nm: float(t_all[i, int(np.flatnonzero(ks == kk)[0])]) for i, nm in enumerate(names)}
    order = sorted(t_k, key=lambda nm: -t_k[nm])
    channels = [nm for nm in order if t_k[nm] >= CHANGE_T] or order[:1]
    return {"n": N, "series": names, "statistic": float(S[0]), "p": float((1 + hits) / (1 + permutations)), "change_at": kk,
            "channels": channels, "t": t_k, "shapes": {nm: _shape(np.asarray(series[nm], dtype=float), kk) for nm in channels}}


def test_series(series: dict[str, np.ndarray], covariates=None, alpha: float = ALPHA, permutations: int = PERMUTATIONS,
                seed: int = 0, combined: bool = True) -> dict[str, dict]:
    """:func:`change_point` of every series, Holm-corrected over them at family-wise ``alpha``,
    and with ``combined`` their :func:`combined_change` under the key :data:`COMBINED`.

    Args:
        series: name -> (N,) series in throw order (all of one length N).
        covariates: as :func:`change_point` (shared by every series).

    Returns:
        name -> the change_point result plus "p_holm" and "drifting" (p_holm < alpha: this series
        changes, by its own test); COMBINED -> the combined_change result (absent where no
        series is usable), its "p_holm" and "drifting" set by :func:`holm` over the combined rows
        of one diagnosis (:func:`verdict.drift_of`), here over this row alone.
    """
    rows = {name: change_point(x, covariates, permutations, seed) for name, x in series.items()}
    holm(rows.values(), alpha)
    if combined and (comb := combined_change(series, covariates, permutations, seed)) is not None:
        rows[COMBINED] = comb
        holm([comb], alpha)
    return rows


def holm(rows: Iterable[dict], alpha: float = ALPHA) -> None:
    """Holm's step-down correction over rows with a "p" (change tests of one family, or the
    combined tests of one diagnosis), in place: each row's "p_holm" and "drifting" (p_holm < alpha)."""
    rows = sorted(rows, key=lambda r: r["p"])
    running = 0.0
    for i, row in enumerate(rows):
        running = max(running, min(1.0, (len(rows) - i) * row["p"]))
        row["p_holm"] = running
        row["drifting"] = bool(running < alpha)


def split_halves(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(early, late) (n,) float throw weights: the first and the second half in throw order (the
    middle throw of an odd n in neither)."""
    h = n // 2
    early, late = np.zeros(n), np.zeros(n)
    early[:h] = 1.0
    late[n - h:] = 1.0
    return early, late


def describe(name: str, row: dict, throw_ids: list[str] | None = None, unit: str = "sigma", p: float | None = None) -> str:
    """One phrase for a drifting series: where, since which throw, how fast (``p``: the p to quote,
    default the row's own p_holm)."""
    k = row["change_at"]
    since = f"throw {throw_ids[k]} (the {k + 1}th of {row['n']})" if throw_ids and k is not None else f"throw {k}"
    how = (f"a step of {row['step']:+.3g} {unit}" if row["shape"] == "step"
           else f"{row['slope_per_throw']:+.3g} {unit} per throw")
    p = row["p_holm"] if p is None else p
    return f"{name} changes since {since}: mean {row['mean_before']:+.3g} -> {row['mean_after']:+.3g} {unit} ({how}; p = {p:.2g})"


def describe_combined(row: dict, throw_ids: list[str] | None = None, unit: str = "sigma") -> list[str]:
    """Phrases for a changing :func:`combined_change` row: each of its channels (at most three) at
    the common split, with the combined test's p."""
    return [describe(ch, {**row["shapes"][ch], "n": row["n"]}, throw_ids, unit, row["p_holm"]) for ch in row["channels"][:3]]
