"""ONNX policy runner with manifest checks.

A policy version is an ONNX file plus a JSON manifest beside it (``<name>.onnx`` and
``<name>.json``), written by ``sim_twin.training.export``. The runtime refuses a policy whose manifest
does not match what this runtime computes (mode, joint order, observation layout, control period,
release threshold) or whose file does not hash to the manifest's SHA-256, and checks the ONNX
graph's input/output shapes and that it returns finite actions.

Manifest fields (``format`` = ``slinger-policy/1``): name, mode, joint_order,
observation_layout [[block, size], ...] (its history blocks declare the policy's history length,
runtime.observation.history_steps_of_layout), observation_size, action_size, control_period_s,
release_threshold, target_range_m [min, max], onnx_sha256, input_name, output_name, training {...};
optional ``aim_correction`` (a version adapted to a site, runtime.aim: checked against the copy
sealed in the ONNX file's metadata) and ``site_profile`` (the site's fitted reality profile, used
by the server's previews; not read here).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from runtime.aim import ONNX_METADATA_KEY, AimCorrection, canonical_json
from runtime.machine import JOINT_NAMES
from runtime.observation import (
    CONTROL_PERIOD_S,
    HISTORY_STEPS,
    MAX_HISTORY_STEPS,
    RELEASE_THRESHOLD,
    history_steps_of_layout,
    num_actions,
    observation_layout,
    observation_size,
)

MANIFEST_FORMAT = "slinger-policy/1"

POLICY_THREADS_ENV = "SLINGER_POLICY_THREADS"
"""Environment variable: onnxruntime intra-op threads of a policy session (default 1; 0 takes
onnxruntime's own defaults, a thread per physical core spinning between calls)."""


class PolicyError(ValueError):
    """A policy file or manifest is unusable; the message says why."""


def session_options(threads: int | None = None) -> Any:
    """onnxruntime session options for a policy: ``threads`` intra-op threads (default
    ``$SLINGER_POLICY_THREADS``, else 1), one inter-op thread and no spin-waiting between calls;
    with 0 onnxruntime's own defaults (a thread per physical core, spinning between calls).

    The policy is an MLP evaluated on one observation per 80 ms control step (a few µs of work):
    onnxruntime's default pool, a thread per physical core that spins between calls, buys nothing
    there and takes the cores from the 100 Hz controller beside it, and from the other processes of
    a site matrix (each of its workers holds a session). Spinning and pool size are onnxruntime's
    ``session.intra_op.allow_spinning`` and ``intra_op_num_threads``
    (https://onnxruntime.ai/docs/performance/tune-performance/threading.html).

    Raises:
        PolicyError: ``$SLINGER_POLICY_THREADS`` is not a whole number ≥ 0.
    """
    import onnxruntime as ort

    if threads is None:
        raw = os.environ.get(POLICY_THREADS_ENV, "1")
        try:
            threads = int(raw)
        except ValueError:
            threads = -1
        if threads < 0:
            raise PolicyError(f"{POLICY_THREADS_ENV} must be a whole number >= 0, got {raw!r}")
    opts = ort.SessionOptions()
    if threads == 0:
        return opts
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return opts


def sha256_of(path: str | Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def expected_manifest_fields(mode: str, history_steps: int = HISTORY_STEPS) -> dict:
    """The manifest fields that must equal this runtime's own definitions for ``mode`` and a policy
    reading ``history_steps`` control steps of joint history (runtime.observation)."""
    return {
        "format": MANIFEST_FORMAT,
        "mode": mode,
        "joint_order": list(JOINT_NAMES),
        "observation_layout": [list(b) for b in observation_layout(mode, history_steps)],
        "observation_size": observation_size(mode, history_steps),
        "action_size": num_actions(mode),
        "control_period_s": CONTROL_PERIOD_S,
        "release_threshold": RELEASE_THRESHOLD,
    }


@dataclass
class PolicyRunner:
    """A loaded, checked policy. Use :meth:`load`; call :meth:`act` once per control step.

    Attributes:
        manifest: the parsed manifest.
        path: the ONNX file.
    """

    manifest: dict
    path: Path
    _session: Any  # onnxruntime.InferenceSession
    aim_correction: AimCorrection | None = None
    _input_name: str | None = field(default=None, repr=False, compare=False)

    @property
    def mode(self) -> str:
        return self.manifest["mode"]

    @property
    def version(self) -> str:
        return self.manifest["name"]

    @property
    def sha256(self) -> str:
        return self.manifest["onnx_sha256"]

    @property
    def history_steps(self) -> int:
        """Control steps of joint history the policy reads (its manifest's observation_layout)."""
        return history_steps_of_layout(self.mode, self.manifest["observation_layout"])

    @property
    def target_range_m(self) -> tuple[float, float]:
        lo, hi = self.manifest["target_range_m"]
        return float(lo), float(hi)

    @classmethod
    def load(cls, onnx_path: str | Path, manifest_path: str | Path | None = None) -> PolicyRunner:
        """Load and check a policy.

        Args:
            onnx_path: the ONNX file.
            manifest_path: its manifest; default: the same path with suffix ``.json``.

        Raises:
            PolicyError: missing files, a manifest that does not match this runtime, a SHA-256
                mismatch, a bad ``$SLINGER_POLICY_THREADS`` (:func:`session_options`), a file
                onnxruntime cannot load, wrong input/output shapes, or
                non-finite actions on a zero observation.
        """
        import onnxruntime as ort

        onnx_path = Path(onnx_path)
        manifest_path = Path(manifest_path) if manifest_path else onnx_path.with_suffix(".json")
        if not onnx_path.is_file():
            raise PolicyError(f"policy file not found: {onnx_path}")
        if not manifest_path.is_file():
            raise PolicyError(f"policy manifest not found: {manifest_path}")
        try:
            manifest = json.loads(manifest_path.read_text())
        except json.JSONDecodeError as e:
            raise PolicyError(f"manifest {manifest_path} is not JSON: {e}") from e
        mode = manifest.get("mode")
        if mode not in ("2d", "3d"):
            raise PolicyError(f"manifest mode must be '2d' or '3d', got {mode!r}")
        try:
            history = history_steps_of_layout(mode, manifest.get("observation_layout") or [])
        except ValueError as e:
            raise PolicyError(f"manifest observation_layout does not match this runtime: {e}") from e
        for key, want in expected_manifest_fields(mode, history).items():
            if manifest.get(key) != want:
                raise PolicyError(f"manifest {key} = {manifest.get(key)!r} does not match this runtime ({want!r})")
        for key in ("name", "onnx_sha256", "target_range_m"):
            if key not in manifest:
                raise PolicyError(f"manifest lacks {key!r}")
        digest = sha256_of(onnx_path)
        if digest != manifest["onnx_sha256"]:
            raise PolicyError(f"SHA-256 mismatch: file {digest[:12]}…, manifest {manifest['onnx_sha256'][:12]}…")
        opts = session_options()
        try:
            session = ort.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types
            raise PolicyError(f"onnxruntime cannot load {onnx_path.name}: {e}") from e
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise PolicyError("policy graph must have one input and at least one output")
        n_obs = observation_size(mode, history)
        if inputs[0].shape[-1] != n_obs:
            raise PolicyError(f"policy input has {inputs[0].shape[-1]} features, mode {mode} with {history} history steps "
                              f"needs {n_obs}{_history_hint(mode, inputs[0].shape[-1])}")
        if outputs[0].shape[-1] != num_actions(mode):
            raise PolicyError(f"policy output has {outputs[0].shape[-1]} values, mode {mode} needs {num_actions(mode)}")
        runner = cls(manifest, onnx_path, session, _aim_correction(manifest, session))
        probe = runner.act(np.zeros(n_obs, dtype=np.float32))
        if not np.all(np.isfinite(probe)):
            raise PolicyError("policy returns non-finite actions on a zero observation")
        return runner

    def aim_target(self, target_m) -> np.ndarray:
        """The target (3,) the policy is given for a requested target (3,), machine frame, m:
        the requested one, or the site's aim correction applied to it (runtime.aim)."""
        if self.aim_correction is None:
            return np.asarray(target_m, dtype=float)
        return self.aim_correction.aim(target_m)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """One policy evaluation.

        Args:
            obs: (observation_size,) observation (see runtime.observation).

        Returns:
            (num_actions,) float32 action.

        Raises:
            PolicyError: if the observation has the wrong size or is not finite.
        """
        obs = np.asarray(obs, dtype=np.float32).reshape(1, -1)
        if obs.shape[1] != self.manifest["observation_size"]:
            raise PolicyError(f"observation has {obs.shape[1]} values, expected {self.manifest['observation_size']}")
        if not np.isfinite(obs).all():
            raise PolicyError("non-finite observation")
        name = self._input_name
        if name is None:  # looked up once: get_inputs() builds its NodeArgs again on every call
            name = self._input_name = self._session.get_inputs()[0].name
        return self._session.run(None, {name: obs})[0][0]


def _history_hint(mode: str, n_inputs) -> str:
    """'' or, where an input of ``n_inputs`` values fits ``mode`` with another history length, a
    clause naming it (for the refusal message)."""
    for steps in range(1, MAX_HISTORY_STEPS + 1):
        if n_inputs == observation_size(mode, steps):
            return f" (it fits {steps} history steps: declare history_steps {steps})"
    return ""


def _aim_correction(manifest: dict, session) -> AimCorrection | None:
    """The manifest's aim correction, checked against the one sealed in the ONNX metadata.

    Raises:
        PolicyError: an invalid table, or manifest and file disagree (one has it, the other
            not, or the tables differ).
    """
    block = manifest.get("aim_correction")
    sealed = session.get_modelmeta().custom_metadata_map.get(ONNX_METADATA_KEY)
    if block is None and sealed is None:
        return None
    if block is None or sealed is None or canonical_json(block) != sealed:
        raise PolicyError("the manifest's aim_correction does not match the one sealed in the ONNX file")
    try:
        return AimCorrection.from_block(block)
    except ValueError as e:
        raise PolicyError(str(e)) from e


def build_manifest(
    onnx_path: str | Path,
    mode: str,
    name: str,
    target_range_m: tuple[float, float],
    training: dict | None = None,
    input_name: str = "obs",
    output_name: str = "actions",
    history_steps: int = HISTORY_STEPS,
) -> dict:
    """The manifest of an exported policy (see module doc) reading ``history_steps`` control steps
    of joint history, hashing ``onnx_path``."""
    return {
        **expected_manifest_fields(mode, history_steps),
        "name": name,
        "target_range_m": [float(target_range_m[0]), float(target_range_m[1])],
        "onnx_sha256": sha256_of(onnx_path),
        "input_name": input_name,
        "output_name": output_name,
        "training": training or {},
    }


def write_manifest(onnx_path: str | Path, manifest: dict) -> Path:
    """Write ``manifest`` beside ``onnx_path`` as ``<stem>.json``; returns its path."""
    path = Path(onnx_path).with_suffix(".json")
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    return path
