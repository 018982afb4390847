"""Policy versions: upload with validation, a small twin evaluation, promotion to machines over
Zenoh (the runtime fetches the file from this server, checks it and loads it between throws),
rollback to the previous version, and the deployment record.

Zenoh entities (declared by :meth:`PolicyService.start`): the queryable keys.POLICY_FILES (serves
``<data_dir>/policies/<sha256>.onnx``) and a subscriber of keys.ALL_POLICY_STATUS (a runtime's
PolicyUpdate turns the offered deployment active or failed).
"""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Callable
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.observation import HISTORY_STEPS
from runtime.policy import build_manifest
from runtime.protocol import keys
from runtime.protocol.messages import (
    PolicyOffer,
    PolicyUpdate,
    ValidationError,
    decode,
)
from server.accounts.auth import audit
from server.db.models import PolicyDeployment, PolicyVersion
from server.db.types import utcnow
from server.db.upsert import insert_if_absent
from server.errors import Conflict, NotFound, Refused
from server.fleet.link import Fleet, RuntimeUnavailable
from server.fleet.results import ResultStore, ensure_machine
from server.policies.validation import ValidationLimits, validate

log = logging.getLogger(__name__)
MAX_POLICY_BYTES = 50 * 1024 * 1024


class PolicyService:
    """Args: fleet (None in a worker: no fleet link, so no promotion, rollback or policy files over
    Zenoh), sessions, store (policy files), settings (eval_distances_m, eval_throws), jobs
    (server.jobs.JobQueue: the twin evaluation of an upload runs as a job in a worker).

    ``on_deployment``: None, or called with (machine id, mode, status) after a runtime's
    PolicyUpdate settled a deployment (``active`` or ``failed``): the machine's rollback target may
    have moved (server.services has the live hub announce it:
    :meth:`server.console.live.LiveHub.deployment_changed`)."""

    def __init__(self, fleet: Fleet | None, sessions: sessionmaker[Session], store: ResultStore, settings, jobs,
                 on_deployment: Callable[[str, str, str], None] | None = None):
        self.fleet, self.sessions, self.store, self.settings, self.jobs = fleet, sessions, store, settings, jobs
        self._decls: list = []
        self.on_deployment = on_deployment

    @property
    def _link(self) -> Fleet:
        """The fleet link; RuntimeError in a service made without one (a worker's)."""
        if self.fleet is None:
            raise RuntimeError("this PolicyService has no fleet link (a worker's): it cannot reach runtimes")
        return self.fleet

    # --- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        s = self._link.session
        self._decls = [s.declare_queryable(keys.POLICY_FILES, self._on_file_query, complete=True),
                       s.declare_subscriber(keys.ALL_POLICY_STATUS, self._on_update)]

    def stop(self) -> None:
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)

    # --- upload ------------------------------------------------------------------------------
    def upload(self, data: bytes, mode: str, name: str, target_range_m: tuple[float, float], notes: str | None,
               username: str, evaluate: bool = True, history_steps: int = HISTORY_STEPS) -> PolicyVersion:
        """Validate and store a policy version reading ``history_steps`` control steps of joint
        history (runtime.observation); start its twin evaluation.

        Raises:
            Refused: with the reason (not ONNX, wrong shapes for the mode and history, non-finite
                actions on a small observation sweep, over the memory or time limit of the
                check, bad range). Conflict: this file is already a version.
        """
        if not data:
            raise Refused("empty file")
        if len(data) > MAX_POLICY_BYTES:
            raise Refused(f"file larger than {MAX_POLICY_BYTES // 2**20} MiB")
        lo, hi = target_range_m
        if not (0 < lo < hi):
            raise Refused("target range must satisfy 0 < min < max")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "upload.onnx"
            path.write_bytes(data)
            manifest = build_manifest(path, mode, name, (lo, hi), {"notes": notes or "", "uploaded_by": username},
                                      history_steps=history_steps)
            path.with_suffix(".json").write_text(json.dumps(manifest))
            # loaded and probed in a limited child process, never in the API (a tiny file can ask
            # onnxruntime for gigabytes): server.policies.validation
            verdict = validate(path, ValidationLimits.from_settings(self.settings, upload=True))
            if not verdict["passed"]:
                reason = verdict["reason"].removeprefix("the policy does not load: ")
                if "onnxruntime cannot load" in reason:
                    reason = f"not a loadable ONNX model: {reason.split(': ', 1)[-1][:300]}"
                raise Refused(reason)
            return self.add_version(manifest, path, username, notes, evaluate)

    def add_version(self, manifest: dict, path: Path, username: str, notes: str | None = None, evaluate: bool = True,
                    action: str = "policy_upload") -> PolicyVersion:
        """Store a checked policy file with its manifest as a new version (audited as
        ``action``) and start its twin evaluation; ``upload`` and ``slinger adapt`` results
        (server.analysis.adaptation) come in here.

        Raises:
            Conflict: this file is already a version (also when the same file is added twice at
                once: the second insert waits for the first and adds nothing).
        """
        sha, already = manifest["onnx_sha256"], "this ONNX file is already a policy version"
        with self.sessions() as db:
            if db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == sha)) is not None:
                raise Conflict(already)  # before the file is written
        rel = self.store.store_policy_file(manifest, path)  # named by its SHA-256: a second writer writes the same bytes
        name, mode = manifest["name"], manifest["mode"]
        with self.sessions.begin() as db:
            if not insert_if_absent(db, PolicyVersion, ["sha256"], name=name, mode=mode, sha256=sha, manifest=manifest,
                                    onnx_path=rel, notes=notes, uploaded_by=username,
                                    evaluation_status="pending" if evaluate else None):
                raise Conflict(already)
            row = db.scalars(select(PolicyVersion).where(PolicyVersion.sha256 == sha)).one()
            audit(db, username, action, str(row.id), name=name, mode=mode, sha256=sha)
        if evaluate:
            self._submit_evaluation(row.id, manifest["target_range_m"], username)
        return row

    def evaluate(self, version_id: int, username: str) -> PolicyVersion:
        """(Re-)evaluate a stored version in the twin (a deployed one that was never evaluated,
        or one to evaluate again); audited as ``policy_evaluate``.

        Raises:
            NotFound: an unknown version. Conflict: its evaluation is pending or running.
        """
        with self.sessions.begin() as db:
            row = db.get(PolicyVersion, version_id)
            if row is None:
                raise NotFound(f"no policy version {version_id}")
            if row.evaluation_status in ("pending", "running"):
                raise Conflict(f"the evaluation of {row.name} is already {row.evaluation_status}")
            row.evaluation_status = "pending"
            rng = (row.manifest or {}).get("target_range_m") or [5.0, 10.7]
            audit(db, username, "policy_evaluate", str(row.id), name=row.name, mode=row.mode)
        self._submit_evaluation(version_id, rng, username)
        with self.sessions() as db:
            return db.get_one(PolicyVersion, version_id)

    def _submit_evaluation(self, version_id: int, target_range_m, username: str) -> None:
        lo, hi = target_range_m
        distances = list(self.settings.eval_distances_m) or [
            round(x * 2) / 2 for x in np.linspace(lo + 0.5, hi - 0.5, 3)]
        self.jobs.submit("evaluation", {"version_id": version_id, "distances_m": distances,
                                        "throws": self.settings.eval_throws},
                         subject=str(version_id), requested_by=username)

    # --- promotion ---------------------------------------------------------------------------
    def promote(self, version_id: int, machine_ids: list[str], username: str, action: str = "promote") -> list[PolicyDeployment]:
        """Offer the version to each machine; returns one deployment row per machine (status
        ``offered`` when the runtime accepted the offer, ``failed`` with the reason otherwise).

        Raises:
            NotFound: unknown version. Conflict: no file, or (``Settings.require_validation``,
                not for a rollback: the machine ran that version before) the version has not
                passed its validation (:func:`validation_refusal`; condition ``validation``).
        """
        with self.sessions() as db:
            version = db.get(PolicyVersion, version_id)
        if version is None:
            raise NotFound(f"no policy version {version_id}")
        if not version.onnx_path or not (self.store.data_dir / version.onnx_path).is_file():
            raise Conflict(f"the server has no file of {version.name}; upload it")
        if action == "promote" and getattr(self.settings, "require_validation", False):
            refusal = validation_refusal(version)
            if refusal is not None:
                raise Conflict(refusal, condition="validation")
        out = []
        for mid in machine_ids:
            info = self._link.fresh_info(mid, max_age_s=0.0, timeout_s=2.0)
            previous = next((p.sha256 for p in (info.policies if info else []) if p.mode == version.mode), None)
            # the row exists before the offer: the runtime's confirmation may come back at once
            with self.sessions.begin() as db:
                ensure_machine(db, mid, simulated=bool(info and info.simulated))
                dep = PolicyDeployment(machine_id=mid, mode=version.mode, policy_version_id=version.id,
                                       previous_sha256=previous, status="offered", requested_by=username)
                db.add(dep)
            status, reason = "offered", None
            if info is None:
                status, reason = "failed", f"the runtime of {mid} is offline"
            else:
                try:
                    offer = PolicyOffer(machine_id=mid, mode=version.mode, version=version.name, sha256=version.sha256,
                                        manifest=version.manifest)
                    ack = self._link.offer_policy(offer, username)
                    if not ack.accepted:
                        status, reason = "failed", ack.reason
                except (RuntimeUnavailable, ValidationError, ValueError) as e:
                    status, reason = "failed", str(e)
            with self.sessions.begin() as db:
                dep = db.get_one(PolicyDeployment, dep.id)
                if status == "failed":
                    dep.status, dep.reason = status, reason
                audit(db, username, action, mid, policy_version=version.name, policy_version_id=version.id,
                      mode=version.mode, status=status, reason=reason)
            out.append(dep)
        return out

    def rollback_target(self, machine_id: str, mode: str) -> PolicyVersion | None:
        """The version ``machine_id`` ran for ``mode`` before its last active deployment, or None
        (nothing to roll back to)."""
        with self.sessions() as db:
            last = db.scalar(select(PolicyDeployment).where(
                PolicyDeployment.machine_id == machine_id, PolicyDeployment.mode == mode,
                PolicyDeployment.status == "active").order_by(PolicyDeployment.requested_at.desc(), PolicyDeployment.id.desc()))
            if last is None or not last.previous_sha256:
                return None
            return db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == last.previous_sha256))

    def rollback(self, machine_id: str, mode: str, username: str) -> PolicyDeployment:
        """Promote the version the machine ran before its last active deployment for ``mode``.

        Raises:
            Conflict: there is no earlier version to go back to.
        """
        prev = self.rollback_target(machine_id, mode)
        if prev is None:
            raise Conflict(f"no previous {mode} policy version of {machine_id} to roll back to")
        return self.promote(prev.id, [machine_id], username, action="rollback")[0]

    # --- Zenoh callbacks ---------------------------------------------------------------------
    def _on_file_query(self, query) -> None:
        sha = str(query.key_expr).rsplit("/", 1)[-1]
        path = self.store.data_dir / "policies" / f"{sha}.onnx"
        if len(sha) != 64 or not all(c in "0123456789abcdef" for c in sha) or not path.is_file():
            query.reply_err(f"no policy file {sha[:16]}".encode())
            return
        query.reply(str(query.key_expr), path.read_bytes())

    def _on_update(self, sample) -> None:
        try:
            msg = decode(PolicyUpdate, sample.payload.to_bytes())
        except ValidationError:
            log.warning("malformed PolicyUpdate dropped")
            return
        self._link.forget_info(msg.machine_id)
        with self.sessions.begin() as db:
            dep = db.scalar(select(PolicyDeployment).join(PolicyVersion).where(
                PolicyDeployment.machine_id == msg.machine_id, PolicyDeployment.mode == msg.mode,
                PolicyDeployment.status == "offered", PolicyVersion.sha256 == msg.sha256,
            ).order_by(PolicyDeployment.id.desc()))
            if dep is None:
                return
            dep.status = "active" if msg.status == "loaded" else "failed"
            dep.reason, dep.confirmed_at = msg.reason, utcnow()
            status = dep.status
        log.info("machine %s %s policy %s: %s", msg.machine_id, msg.mode, msg.version, msg.status)
        if self.on_deployment is not None:
            self.on_deployment(msg.machine_id, msg.mode, status)


def evaluate_version(sessions: sessionmaker[Session], data_dir: Path, version_id: int, distances_m: list[float],
                     throws: int, progress, limits: ValidationLimits | None = None) -> dict:
    """Validate policy version ``version_id`` (server.policies.validation, in a limited child
    process: observation sweep and twin throws over its whole target range; ``limits``), then
    run the paper's protocol on a small sample (``throws`` per distance), in a worker (job kind
    ``evaluation``); the report (with the validation verdict under ``validation``) and the status
    go to the version's row as well: ``failed`` with the reason when the validation failed.
    ``progress(fraction, message)`` after every distance; a cancel stops the validation's child
    within one poll (50 ms).

    Raises:
        server.jobs.JobCancelled: from ``progress`` (the row is left ``failed``: cancelled).
    """
    from server.jobs.store import JobCancelled
    from sim_twin.evaluation.evaluate import summarise, throw_batch  # the protocol's own throw loop

    with sessions.begin() as db:
        row = db.get_one(PolicyVersion, version_id)
        if row.onnx_path is None:
            raise ValueError(f"policy version {version_id} ({row.name}) has no ONNX file to evaluate")
        row.evaluation_status = "running"
        mode, path = row.mode, str(Path(data_dir) / row.onnx_path)
        site = row.manifest.get("site_profile")  # a version adapted to a site is evaluated on that site
    profile_path, profile_name = None, "nominal"
    if site:
        profile_path = str(Path(path).with_suffix(".site_profile.json"))
        Path(profile_path).write_text(json.dumps({**site, "uncertainty": {}}))
        profile_name = site.get("name", "site")
    metrics: dict[str, Any] = {"error": "cancelled"}
    status = "failed"
    try:
        progress(0.0, "validation: observation sweep and twin throws over the target range")
        verdict = validate(path, limits or ValidationLimits(), check_cancel=lambda: progress(0.0, None),
                           seed=version_id)
        if not verdict["passed"]:
            metrics = {"validation": verdict, "error": f"validation failed: {verdict['reason']}"}
            log.warning("policy version %d failed validation: %s", version_id, verdict["reason"])
            return metrics
        targets = []
        for i, d in enumerate(distances_m):
            progress(i / len(distances_m), f"{throws} throws at {d:.1f} m")
            seeds = [version_id * 1000 + i * 100 + k for k in range(throws)]
            targets.append(summarise(d, throw_batch(path, mode, d, seeds, profile_path)))
        metrics = {"protocol": "paper Sec. IV-A (small sample)", "throws_per_target": throws,
                   "profile": profile_name, "targets": targets, "validation": verdict}
        status = "done"
    except JobCancelled:
        raise
    except Exception as e:
        log.exception("evaluation of policy version %d failed", version_id)
        metrics = {"error": str(e)}
        raise
    finally:
        with sessions.begin() as db:
            row = db.get_one(PolicyVersion, version_id)
            row.metrics, row.evaluation_status = metrics, status
        log.info("policy version %d evaluated: %s", version_id, status)
    return metrics


OFFER_TIMEOUT_S = 120.0
"""A promotion still ``offered`` this long after it was requested failed: the runtime never
confirmed it (it is offline, or never got between throws)."""


def expire_stale_offers(db: Session, now: datetime | None = None, timeout_s: float = OFFER_TIMEOUT_S) -> int:
    """Mark deployments left ``offered`` for longer than ``timeout_s`` as failed, with the reason.

    Called before deployments are listed (no background timer). Returns how many were expired;
    the caller commits.
    """
    cutoff = (now or utcnow()) - timedelta(seconds=timeout_s)
    rows = db.scalars(select(PolicyDeployment).where(
        PolicyDeployment.status == "offered", PolicyDeployment.requested_at < cutoff)).all()
    for row in rows:
        row.status, row.reason = "failed", f"no confirmation from the runtime within {timeout_s:.0f} s"
    return len(rows)


def validation_refusal(version: PolicyVersion) -> str | None:
    """Why ``version`` may not be promoted yet (its validation has not passed), or None."""
    verdict = (version.metrics or {}).get("validation") or {}
    if version.evaluation_status == "done" and verdict.get("passed"):
        return None
    if version.evaluation_status in (None, "pending", "running"):
        return (f"policy version {version.name} has not been validated yet (evaluation "
                f"{version.evaluation_status or 'not started'}): wait for its evaluation to finish")
    why = verdict.get("reason") or (version.metrics or {}).get("error") or version.evaluation_status
    return f"policy version {version.name} failed its validation: {why}"
