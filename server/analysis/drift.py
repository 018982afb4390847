"""Drift watch: each machine's landed throws are watched for an accuracy drift beyond noise.

Every landed throw's impact error e_t (downrange, crossrange, m; stored at ingest,
runtime.throw_geometry) feeds a two-sided tabular CUSUM per axis (E. S. Page, "Continuous
inspection schemes", Biometrika 41 (1954) 100-115; D. C. Montgomery, Introduction to Statistical
Quality Control, 7th ed., section 9.1) on throws standardised against an estimated baseline whose
uncertainty is accounted for (self-starting CUSUM: D. M. Hawkins, "Self-starting CUSUM charts for
location and scale", The Statistician 36 (1987); D. M. Hawkins and D. H. Olwell, Cumulative Sum
Charts and Charting for Quality Improvement, Springer 1998, the chapter on self-starting charts):

    T_t = (e_t - xbar) / s * sqrt(m / (m + 1)),   u_t = Phi^-1(F_t(T_t; df)),
    C+_t = max(0, C+_{t-1} + u_t - K),   C-_t = max(0, C-_{t-1} - u_t - K)

with xbar the mean of the m throws of the reference, s the pooled spread with df degrees of
freedom, F_t the Student t distribution function and Phi^-1 the standard normal quantile. The
transform u = Phi^-1(F_t(T; df)) is computed by Wallace's normal approximation to Student's t
(D. L. Wallace, "Bounds on normal approximations to Student's and the chi-square distributions",
Ann. Math. Statist. 30 (1959) 1121-1130; :func:`t_to_normal`): the watch's df are at least 29,
where it is within 0.0014 of the exact transform for |u| < 4 and 0.009 beyond (checked against
scipy in tests/test_drift.py). It needs numpy only: the API server carries no scipy (the server
wheel does not depend on it, and scipy.special alone would add about 27 MiB to the process).
For normal errors whose mean and spread did not change, T_t is Student t with df degrees of
freedom (e_t is independent of xbar and s, and e_t - xbar has variance sigma^2 (1 + 1/m)), so u_t
is N(0, 1) whatever the machine's true mean and spread: the decision limit does not depend on how
well 30 throws happened to estimate them. The reference is

* for the first BASELINE_THROWS landed throws the watch sees for the machine: the baseline, no test;
* for the next GUARD_THROWS throws: the baseline's mean (m = BASELINE_THROWS), and the spread pooled
  from the baseline's and these throws' own spreads about their own means (df = m - 1 + j - 1 after
  j >= 2 of them), so a shift right after the baseline is neither absorbed into the mean it is
  measured against nor inflates the spread;
* from then on: every earlier throw (m = t - 1, df = m - 1), Hawkins's self-starting form, whose
  u_t are independent N(0, 1) in control: the baseline keeps growing while the machine is in
  control, and its error shrinks with it.

The spread s is at least the impact sensor's declared noise (SIGMA_FLOOR_M); where the estimate is
below it, s = SIGMA_FLOOR_M is taken as known and u_t = T_t (normal). During the guard throws the
u_t share the baseline mean's error and are not independent; K = 0.4 and H = 10 are therefore
chosen by simulation (CHOSEN; tests/test_drift.py, fixed seeds, normal noise on both axes, 400
runs each): a false alarm in 2.5 % of noise-only runs of 100 throws after the baseline at 5 cm
noise (the floor) and 4.25 % at 10 cm (the floor never binds), and a 1 sigma downrange shift found
within 30 throws in 86.25 % of runs where it starts right after the baseline and 88 % where it
starts after 100 more in-control throws (5 cm noise). tests/benchmarks/bench_drift.py measures
the same on more runs and over 500 throws (1000 runs, seed 3: false alarms in 2.3 % of the runs
within 100 throws and 6.8 % within 500 at 5 cm, 4.1 % and 10.5 % at 10 cm; the previous watch
10.3 % and 37.4 %, 23.5 % and 57.5 %; docs/diagnosis.md has the table). With the reference taken as the truth (the previous
watch: mean and spread of the first 30 throws, K = 0.5, H = 8) about 11 % of the noise-only runs
of 100 throws raised a false alarm: a baseline mean one standard error (0.18 sigma) off cuts the
in-control average run length of each one-sided sum from about 19000 throws to about 1700
(Siegmund's approximation, D. Siegmund, Sequential Analysis, Springer 1985; Montgomery eq. 9.26:
ARL = (exp(-2 D b) + 2 D b - 1) / (2 D^2), D = delta - K, b = H + 1.166). With known mean and
spread, K = 0.4 and H = 10 give 17 throws to a 1 sigma shift, 10 to 1.5 sigma and about 24000
per one-sided sum in control (the same approximation).

On an alarm the watch

1. records an alert on the machine (``<data_dir>/drift/<machine>.json``, :meth:`DriftWatch.alert`;
   the live hub adds it to the machine state as ``drift_alert`` and pushes a ``drift`` event on
   /api/live),
2. POSTs it to the webhook URL of the settings (``drift_webhook_url``), when one is set,
3. starts a diagnosis of the throws since the CUSUM's change-point estimate (the last throw at
   which the alarming sum was 0; at least MIN_DIAGNOSIS_THROWS) by itself
   (:meth:`server.analysis.diagnosis.DiagnosisRuns.start`, requested_by ``drift-watch``),
4. offers the adaptation of that diagnosis's result once it is done (``adaptation`` in the
   alert: the diagnosis run to adapt from and its effects; the operator starts it).

The alarm's "since which throw" and "how fast" come from the change test every diagnosis runs
(:func:`sim_twin.diagnosis.stationarity.change_point`: the maximally selected two-sample t over
the split points, permutation p-value) on the alarming axis's errors of the baseline and the
throws since: its change point (when it falls after the baseline and the test gives p below
CHANGE_P) picks the throws the diagnosis gets, else the CUSUM's own estimate; the alert records
the test (``test.change``: p, change point, means before and after, step, slope per throw). The
diagnosis it starts runs the same test again on every channel of those throws.

The statistics then restart with a new baseline (the machine's new normal). The CUSUM state
lives in memory (a restarted server takes a new baseline); alerts persist until acknowledged
(:meth:`DriftWatch.acknowledge`, POST /api/machines/{id}/drift/ack: an operator or admin,
audited as ``drift_ack``; the acknowledged alert is pushed as a ``drift`` event, so the status
strip's drift alarm clears on every open console) and are kept for the record until the next.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

K = 0.4
H = 10.0
BASELINE_THROWS = 30
GUARD_THROWS = 30
"""Throws after the baseline during which the reference mean stays the baseline's (module doc):
a shift right after the baseline is not absorbed into the mean it is measured against."""
SIGMA_FLOOR_M = 0.05
"""Floor of the baseline's impact spread (m): the impact measurement's declared noise (the 5 cm
of a real machine's impact measurement, sim_twin.diagnosis.reallog.RealLogSpec); a baseline of a
few tight throws must not make every later throw an outlier."""
U_CLIP = 1e3
"""Bound of a standardised throw (a t tail beyond double precision gives an infinite normal score;
any value above H alarms alike)."""
METHOD = "two-sided self-starting CUSUM (Page 1954, Hawkins 1987)"
MIN_DIAGNOSIS_THROWS = 8
CHANGE_P = 0.05
"""The change test's change point replaces the CUSUM's estimate when its p is below this (CHOSEN:
the CUSUM has already alarmed; the test only locates the change)."""
CHANGE_PERMUTATIONS = 999
MAX_RECENT = 500
AXES = ("downrange", "crossrange")
DIRECTIONS = {("downrange", 1): "long", ("downrange", -1): "short", ("crossrange", 1): "left", ("crossrange", -1): "right"}
SAFE = re.compile(r"[^A-Za-z0-9_.-]")


@dataclass
class _Moments:
    """Running count, mean and sum of squared deviations of 2-D errors (B. P. Welford, "Note on a
    method for calculating corrected sums of squares and products", Technometrics 4 (1962) 419-420).

    Attributes:
        n: number of errors added; mean: (2,) their mean, m; m2: (2,) sum of squared deviations
            from it, m^2.
    """

    n: int = 0
    mean: np.ndarray = field(default_factory=lambda: np.zeros(2))
    m2: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def add(self, e: np.ndarray) -> None:
        """Add one (2,) error, m."""
        self.n += 1
        d = e - self.mean
        self.mean = self.mean + d / self.n
        self.m2 = self.m2 + d * (e - self.mean)


@dataclass
class Cusum:
    """Two-sided tabular CUSUM on 2-D impact errors of one machine, each throw standardised against
    the reference of the throws before it through the t distribution (module doc).

    Attributes:
        baseline: (n, 2) errors of the baseline throws (until BASELINE_THROWS); baseline_ids their ids.
        mu, sigma: (2,) mean and spread, m, of the reference the latest throw was standardised
            against (None until the baseline is complete); n_ref: its number of throws.
        hi, lo: (2,) the upper and lower sums; last_zero_hi / last_zero_lo: per axis the index
            (in ``since``) of the last throw at which the sum was 0 (change-point estimate).
        since: throw ids observed since the baseline was complete; errors: their (2,) errors.
    """

    baseline: list = field(default_factory=list)
    mu: np.ndarray | None = None
    sigma: np.ndarray | None = None
    n_ref: int = 0
    hi: np.ndarray = field(default_factory=lambda: np.zeros(2))
    lo: np.ndarray = field(default_factory=lambda: np.zeros(2))
    last_zero_hi: np.ndarray = field(default_factory=lambda: np.full(2, -1))
    last_zero_lo: np.ndarray = field(default_factory=lambda: np.full(2, -1))
    since: list = field(default_factory=list)
    errors: list = field(default_factory=list)
    baseline_ids: list = field(default_factory=list)
    _base: _Moments = field(default_factory=_Moments)  # the baseline throws
    _guard: _Moments = field(default_factory=_Moments)  # the GUARD_THROWS throws after it
    _all: _Moments = field(default_factory=_Moments)  # every throw

    def reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The reference the next throw is standardised against (module doc).

        Returns:
            (mean (2,) m, spread (2,) m before the floor, degrees of freedom (2,), m: throws in the mean).

        Raises:
            RuntimeError: the baseline is not complete.
        """
        if self._base.n < BASELINE_THROWS:
            raise RuntimeError("the drift watch's baseline is not complete")
        if len(self.errors) < GUARD_THROWS:
            ss, df = self._base.m2.copy(), float(self._base.n - 1)
            if self._guard.n >= 2:  # pooled with the guard throws' spread about their own mean
                ss, df = ss + self._guard.m2, df + self._guard.n - 1
            return self._base.mean, np.sqrt(ss / df), np.full(2, df), self._base.n
        return self._all.mean, np.sqrt(self._all.m2 / (self._all.n - 1)), np.full(2, float(self._all.n - 1)), self._all.n

    def update(self, throw_id: str, error_m: np.ndarray) -> dict | None:
        """Add one throw's (downrange, crossrange) error, m. Returns the alarm (dict) or None.

        Raises:
            ValueError: an error that is not two finite numbers.
        """
        e = np.asarray(error_m, dtype=float)
        if e.shape != (2,) or not np.all(np.isfinite(e)):
            raise ValueError(f"impact error must be two finite numbers (downrange, crossrange), got {error_m!r}")
        if self._base.n < BASELINE_THROWS:
            self.baseline.append(e)
            self.baseline_ids.append(throw_id)
            self._base.add(e)
            self._all.add(e)
            if self._base.n >= BASELINE_THROWS:
                self.mu, self.sigma, self.n_ref = self._base.mean.copy(), np.maximum(np.sqrt(self._base.m2 / (self._base.n - 1)), SIGMA_FLOOR_M), self._base.n
            return None
        mean, s, df, m = self.reference()
        self.mu, self.sigma, self.n_ref = mean.copy(), np.maximum(s, SIGMA_FLOOR_M), m
        u = standardise(e, mean, s, df, m)
        if len(self.errors) < GUARD_THROWS:
            self._guard.add(e)
        self._all.add(e)
        self.since.append(throw_id)
        self.errors.append(e)
        i = len(self.since) - 1
        self.hi = np.maximum(0.0, self.hi + u - K)
        self.lo = np.maximum(0.0, self.lo - u - K)
        self.last_zero_hi = np.where(self.hi == 0.0, i, self.last_zero_hi)
        self.last_zero_lo = np.where(self.lo == 0.0, i, self.last_zero_lo)
        stats_ = np.stack([self.hi, self.lo])  # (2 sides, 2 axes)
        if stats_.max() <= H:
            return None
        side, ax = np.unravel_index(int(np.argmax(stats_)), stats_.shape)
        start = int((self.last_zero_hi if side == 0 else self.last_zero_lo)[ax]) + 1
        change = _change_test(np.array(self.baseline + self.errors)[:, ax], len(self.baseline), self.baseline_ids + self.since)
        if change["p"] < CHANGE_P and change["change_at"] is not None and change["change_at"] >= len(self.baseline):
            start = min(change["change_at"] - len(self.baseline), len(self.since) - 1)
            change["used"] = True
        recent = np.array(self.errors[start:])
        mu, sigma = self.mu, self.sigma
        return {"axis": AXES[ax], "direction": DIRECTIONS[(AXES[ax], 1 if side == 0 else -1)], "statistic": float(stats_[side, ax]), "change": change,
                "change_after": self.since[start - 1] if start > 0 else None, "throw_ids": self.since[start:],
                "recent": {"n": len(recent), "mean_downrange_m": float(recent[:, 0].mean()), "mean_crossrange_m": float(recent[:, 1].mean())},
                "baseline": {"n": self.n_ref, "mean_downrange_m": float(mu[0]), "mean_crossrange_m": float(mu[1]),
                             "sigma_downrange_m": float(sigma[0]), "sigma_crossrange_m": float(sigma[1])}}


def t_to_normal(t, df) -> np.ndarray:
    """Phi^-1(F_t(t; df)): a Student t value as the standard normal value of the same tail
    probability, by Wallace's approximation (Wallace 1959, module doc; also Johnson, Kotz and
    Balakrishnan, Continuous Univariate Distributions 2, 2nd ed., section 28.8):

        u = sign(t) (8 df + 1) / (8 df + 3) sqrt(df ln(1 + t^2 / df))

    Args:
        t, df: arrays of the same shape (or broadcastable); df > 0 degrees of freedom.

    Returns:
        u, the shape of ``t``. Error against the exact transform: below 0.0014 for |u| < 4 and
        0.009 overall at df >= 29, 0.0011 overall at df >= 100 (tests/test_drift.py).
    """
    t, df = np.asarray(t, dtype=float), np.asarray(df, dtype=float)
    return np.sign(t) * (8.0 * df + 1.0) / (8.0 * df + 3.0) * np.sqrt(df * np.log1p(t * t / df))


def standardise(e, mean, s, df, m: int) -> np.ndarray:
    """A throw's error standardised against a reference estimated from m earlier throws (Hawkins 1987,
    module doc): T = (e - mean) / s * sqrt(m / (m + 1)) is Student t with df degrees of freedom for
    normal errors in control, u = Phi^-1(F_t(T; df)) is then N(0, 1). Where s is below SIGMA_FLOOR_M
    the floor is taken as the known spread and u = T (normal).

    Args:
        e, mean, s, df: (2,) error, reference mean (m), spread (m, before the floor) and degrees of
            freedom per axis; m: throws in the reference mean (>= 2).

    Returns:
        (2,) u, bounded by +-U_CLIP.
    """
    e, mean, s, df = (np.asarray(v, dtype=float) for v in (e, mean, s, df))
    t = (e - mean) / np.maximum(s, SIGMA_FLOOR_M) * np.sqrt(m / (m + 1.0))
    u = t_to_normal(t, df)
    return np.clip(np.where(s < SIGMA_FLOOR_M, t, u), -U_CLIP, U_CLIP)


class DriftWatch:
    """Watches every machine's landed throws (module doc).

    Args:
        sessions: database session factory (reads the stored throw of a result); None when only
            :meth:`observe` is used.
        data_dir: alerts go to ``<data_dir>/drift/<machine>.json``.
        diagnosis: :class:`server.analysis.diagnosis.DiagnosisRuns` (None: no diagnosis is started).
        webhook_url: POST each alert there (JSON), "" for none.
        publish: ``publish(event, data)`` (the live hub's), called with ``("drift", alert)``.
        post: the webhook sender ``post(url, alert)`` (tests; default urllib, 5 s timeout, in a thread).
    """

    def __init__(self, sessions, data_dir: Path, diagnosis=None, webhook_url: str = "", publish: Callable[[str, dict], None] | None = None,
                 post: Callable[[str, dict], None] | None = None):
        self.sessions, self.diagnosis, self.webhook_url, self.publish = sessions, diagnosis, webhook_url or "", publish
        self.root = Path(data_dir) / "drift"
        self._post = post or _post_json
        self._state: dict[str, Cusum] = {}
        self._lock = threading.Lock()

    # --- input ----------------------------------------------------------------------------------
    def on_result(self, throw_id: str) -> None:
        """The fleet's result listener: reads the stored throw and observes it if it landed.
        Never raises (a listener must not break the ingest): errors are logged."""
        try:
            from server.db.models import Throw

            with self.sessions() as db:
                t = db.get(Throw, throw_id)
                if t is None or t.status != "landed" or t.downrange_error_m is None or t.crossrange_error_m is None:
                    return
                machine_id, err = t.machine_id, (t.downrange_error_m, t.crossrange_error_m)
            self.observe(machine_id, throw_id, err)
        except Exception:
            log.exception("drift watch: throw %s not observed", throw_id)

    def observe(self, machine_id: str, throw_id: str, error_m) -> dict | None:
        """One landed throw's (downrange, crossrange) impact error, m. Returns the alert it
        raised, else None.

        Raises:
            ValueError: a malformed error (nothing is recorded).
        """
        with self._lock:
            st = self._state.setdefault(machine_id, Cusum())
            alarm = st.update(throw_id, error_m)
            if alarm is None:
                return None
            self._state[machine_id] = Cusum()  # the new normal gets a new baseline
        return self._raise(machine_id, alarm)

    # --- alerts ---------------------------------------------------------------------------------
    def _raise(self, machine_id: str, alarm: dict) -> dict:
        b = alarm["baseline"]
        ax = alarm["axis"]
        shift = alarm["recent"][f"mean_{ax}_m"] - b[f"mean_{ax}_m"]
        alert = {
            "machine_id": machine_id, "raised_at": datetime.now(UTC).isoformat(), "status": "open",
            "text": (f"accuracy drift: the last {alarm['recent']['n']} landed throws land {abs(shift):.2f} m {alarm['direction']} "
                     f"of the baseline on average ({ax} sigma {b[f'sigma_{ax}_m']:.2f} m over {b['n']} throws)"),
            "test": {"method": METHOD, "k": K, "h": H, "axis": ax, "direction": alarm["direction"],
                     "statistic": alarm["statistic"], "shift_m": shift, "change": alarm.get("change")},
            "baseline": b, "recent": alarm["recent"], "throw_ids": alarm["throw_ids"][-MAX_RECENT:],
            "diagnosis": None, "adaptation": None, "webhook": None,
        }
        if self.diagnosis is not None:
            limit = max(len(alarm["throw_ids"]), MIN_DIAGNOSIS_THROWS)
            try:
                st = self.diagnosis.start(machine_id, limit=limit, requested_by="drift-watch")
                alert["diagnosis"] = {"id": st["id"], "status": st["status"], "throws": limit}
            except Exception as e:  # noqa: BLE001  busy, too few throws: the alert still stands
                alert["diagnosis"] = {"id": None, "status": "not started", "error": f"{type(e).__name__}: {e}"}
        self._write(machine_id, alert)
        log.warning("drift watch %s: %s", machine_id, alert["text"])
        if self.webhook_url:
            threading.Thread(target=self._send, args=(machine_id, alert), daemon=True).start()
        if self.publish is not None:
            self.publish("drift", alert)
        return alert

    def _send(self, machine_id: str, alert: dict) -> None:
        try:
            self._post(self.webhook_url, alert)
            result = {"url": self.webhook_url, "status": "sent"}
        except Exception as e:  # noqa: BLE001
            result = {"url": self.webhook_url, "status": f"failed: {type(e).__name__}: {e}"}
        with self._lock:
            cur = self._read(machine_id)
            if cur is not None and cur.get("raised_at") == alert["raised_at"]:
                cur["webhook"] = result
                self._write(machine_id, cur)

    def alert(self, machine_id: str) -> dict | None:
        """The machine's open or acknowledged alert (None: none), with its diagnosis's state
        refreshed and, once that is done with named or consistent effects, the adaptation offer:
        ``{"diagnosis_id", "effects", "verdict", "how"}``."""
        cur = self._read(machine_id)
        if cur is None:
            return None
        d = cur.get("diagnosis") or {}
        if self.diagnosis is not None and d.get("id") and d.get("status") in ("queued", "running"):
            st = self.diagnosis.get(d["id"]) or {}
            if st.get("status") and st["status"] != d["status"]:
                verdict = st.get("verdict") or {}
                cur["diagnosis"] = {**d, "status": st["status"], "error": st.get("error"),
                                    "verdict": {"answer": verdict.get("answer"), "text": verdict.get("text")} if verdict else None}
                if st["status"] == "done" and verdict.get("effects"):
                    cur["adaptation"] = {"diagnosis_id": d["id"], "effects": verdict["effects"], "verdict": verdict.get("answer"),
                                         "how": f"POST /api/diagnosis/runs/{d['id']}/adapt with the mode to adapt"}
                self._write(machine_id, cur)
        return cur

    def acknowledge(self, machine_id: str, username: str) -> dict | None:
        """Mark the machine's alert acknowledged (kept for the record until the next one) and
        publish it (``("drift", alert)``: every open console clears its drift alarm). An alert
        already acknowledged stays as it was (its first acknowledgement is kept).

        Returns:
            The alert, or None when the machine has none.
        """
        with self._lock:
            cur = self._read(machine_id)
            if cur is None:
                return None
            if cur.get("status") == "acknowledged":
                return cur
            cur.update(status="acknowledged", acknowledged_by=username, acknowledged_at=datetime.now(UTC).isoformat())
            self._write(machine_id, cur)
        if self.publish is not None:
            self.publish("drift", cur)
        return cur

    def alerts(self) -> list[dict]:
        """Every machine's latest alert (open or acknowledged), sorted by machine id: what a
        console that just connected is sent (server.console.live.LiveHub.subscribe)."""
        try:
            paths = sorted(self.root.glob("*.json"))
        except OSError:
            return []
        out = []
        for p in paths:
            try:
                out.append(json.loads(p.read_text()))
            except (OSError, json.JSONDecodeError):
                log.warning("drift watch: unreadable alert file %s skipped", p)
        return sorted(out, key=lambda a: str(a.get("machine_id")))

    def _path(self, machine_id: str) -> Path:
        return self.root / f"{SAFE.sub('_', machine_id)}.json"

    def _read(self, machine_id: str) -> dict | None:
        try:
            return json.loads(self._path(machine_id).read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def _write(self, machine_id: str, alert: dict) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        p = self._path(machine_id)
        tmp = p.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(alert, indent=1))
        tmp.replace(p)


def _change_test(x: np.ndarray, n_baseline: int, ids: list[str]) -> dict:
    """The diagnosis' change test (:func:`sim_twin.diagnosis.stationarity.change_point`) of one
    axis's errors (m, throw order: the baseline, then the throws since), with the throw id after
    the change (``since_throw``) and whether the alarm used its change point (``used``)."""
    from sim_twin.diagnosis.stationarity import change_point

    row = change_point(x, permutations=CHANGE_PERMUTATIONS)
    k = row["change_at"]
    return {"method": "max-t change point, permutation p (sim_twin.diagnosis.stationarity)", "p": row["p"], "change_at": k,
            "since_throw": ids[k] if k is not None and k < len(ids) else None, "after_baseline": k is not None and k >= n_baseline,
            "mean_before_m": row["mean_before"], "mean_after_m": row["mean_after"], "step_m": row["step"],
            "slope_m_per_throw": row["slope_per_throw"], "shape": row["shape"], "used": False}


def _post_json(url: str, data: dict) -> None:
    req = urllib.request.Request(url, data=json.dumps(data).encode(), headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=5.0) as r:  # an operator-set URL
        r.read()
