"""Drift watch: each machine's landed throws are watched for an accuracy drift beyond noise.

Every landed throw's impact error (downrange, crossrange, m; stored at ingest, runtime.throw_geometry)
feeds a two-sided tabular CUSUM per axis (E. S. Page, "Continuous inspection schemes",
Biometrika 41 (1954) 100-115; parameters as in D. C. Montgomery, Introduction to Statistical
Quality Control, 7th ed., section 9.1):

    z_t = (e_t - mu_0) / sigma_0,   C+_t = max(0, C+_{t-1} + z_t - K),   C-_t = max(0, C-_{t-1} - z_t - K)

with mu_0, sigma_0 from the first BASELINE_THROWS landed throws the watch sees for the machine
(sigma_0 at least the impact sensor's declared noise, SIGMA_FLOOR_M), K = 0.5 (tuned to a shift of
1 sigma_0) and H = 8: an alarm when any of the four sums (two axes, two sides) exceeds H.
Siegmund's approximation of the average run length (D. Siegmund, Sequential Analysis, Springer
1985; Montgomery eq. 9.26), ARL = (exp(-2 D b) + 2 D b - 1) / (2 D^2), D = delta - K,
b = H + 1.166, gives 16 throws for a shift of 1 sigma_0 and 9 for 1.5 sigma_0, and about 19000
per one-sided sum in control with known mu_0, sigma_0. Estimating them from 30 throws costs much
of that: tests/test_drift.py bounds, on 200 simulated runs each, the share of noise-only runs of
100 throws with a false alarm (below 20 %) and the share of 1 sigma_0 shifts found within 30
throws (above 80 %).

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

K = 0.5
H = 8.0
BASELINE_THROWS = 30
SIGMA_FLOOR_M = 0.05
"""Floor of the baseline's impact spread (m): the impact measurement's declared noise (the 5 cm
of a real machine's impact measurement, sim_twin.diagnosis.reallog.RealLogSpec); a baseline of a
few tight throws must not make every later throw an outlier."""
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
class Cusum:
    """Two-sided tabular CUSUM on 2-D impact errors of one machine (module doc).

    Attributes:
        baseline: (n, 2) errors of the baseline throws (until BASELINE_THROWS).
        mu, sigma: (2,) baseline mean and spread, m (None until the baseline is complete).
        hi, lo: (2,) the upper and lower sums; last_zero_hi / last_zero_lo: per axis the index
            (in ``since``) of the last throw at which the sum was 0 (change-point estimate).
        since: throw ids observed since the baseline was complete.
    """

    baseline: list = field(default_factory=list)
    mu: np.ndarray | None = None
    sigma: np.ndarray | None = None
    hi: np.ndarray = field(default_factory=lambda: np.zeros(2))
    lo: np.ndarray = field(default_factory=lambda: np.zeros(2))
    last_zero_hi: np.ndarray = field(default_factory=lambda: np.full(2, -1))
    last_zero_lo: np.ndarray = field(default_factory=lambda: np.full(2, -1))
    since: list = field(default_factory=list)
    errors: list = field(default_factory=list)
    baseline_ids: list = field(default_factory=list)

    def update(self, throw_id: str, error_m: np.ndarray) -> dict | None:
        """Add one throw's (downrange, crossrange) error, m. Returns the alarm (dict) or None.

        Raises:
            ValueError: an error that is not two finite numbers.
        """
        e = np.asarray(error_m, dtype=float)
        if e.shape != (2,) or not np.all(np.isfinite(e)):
            raise ValueError(f"impact error must be two finite numbers (downrange, crossrange), got {error_m!r}")
        if self.mu is None or self.sigma is None:  # set together once the baseline is full
            self.baseline.append(e)
            self.baseline_ids.append(throw_id)
            if len(self.baseline) >= BASELINE_THROWS:
                b = np.array(self.baseline)
                self.mu, self.sigma = b.mean(axis=0), np.maximum(b.std(axis=0, ddof=1), SIGMA_FLOOR_M)
            return None
        z = (e - self.mu) / self.sigma
        self.since.append(throw_id)
        self.errors.append(e)
        i = len(self.since) - 1
        self.hi = np.maximum(0.0, self.hi + z - K)
        self.lo = np.maximum(0.0, self.lo - z - K)
        self.last_zero_hi = np.where(self.hi == 0.0, i, self.last_zero_hi)
        self.last_zero_lo = np.where(self.lo == 0.0, i, self.last_zero_lo)
        stats = np.stack([self.hi, self.lo])  # (2 sides, 2 axes)
        if stats.max() <= H:
            return None
        side, ax = np.unravel_index(int(np.argmax(stats)), stats.shape)
        start = int((self.last_zero_hi if side == 0 else self.last_zero_lo)[ax]) + 1
        change = _change_test(np.array(self.baseline + self.errors)[:, ax], len(self.baseline), self.baseline_ids + self.since)
        if change["p"] < CHANGE_P and change["change_at"] is not None and change["change_at"] >= len(self.baseline):
            start = min(change["change_at"] - len(self.baseline), len(self.since) - 1)
            change["used"] = True
        recent = np.array(self.errors[start:])
        mu, sigma = self.mu, self.sigma
        assert mu is not None and sigma is not None  # set with the baseline, before any test
        return {"axis": AXES[ax], "direction": DIRECTIONS[(AXES[ax], 1 if side == 0 else -1)], "statistic": float(stats[side, ax]), "change": change,
                "change_after": self.since[start - 1] if start > 0 else None, "throw_ids": self.since[start:],
                "recent": {"n": len(recent), "mean_downrange_m": float(recent[:, 0].mean()), "mean_crossrange_m": float(recent[:, 1].mean())},
                "baseline": {"n": len(self.baseline), "mean_downrange_m": float(mu[0]), "mean_crossrange_m": float(mu[1]),
                             "sigma_downrange_m": float(sigma[0]), "sigma_crossrange_m": float(sigma[1])}}


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
            "test": {"method": "two-sided CUSUM (Page 1954)", "k": K, "h": H, "axis": ax, "direction": alarm["direction"],
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
