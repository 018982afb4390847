"""Policy validation (server.policies.validation): wall time, verdict and peak resident memory of
the upload check and of the full validation with the default settings, for a harmless fixture
policy, the conditional-NaN policy and the 2 GiB memory-bomb policy of
tests/test_policy_validation.py. Prints JSON (the figures of reports/policy_validation.json).

Run from the repository root::

    PYTHONPATH=$PWD MUJOCO_GL=egl python tests/benchmarks/bench_policy_validation.py
"""

from __future__ import annotations

import json
import platform
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from runtime.policy import sha256_of
from server.config import Settings
from server.policies.validation import ValidationLimits, validate
from tests.fixtures import write_test_policy
from tests.test_policy_validation import conditional_nan_policy, memory_bomb_policy


def main() -> None:
    d = Path(tempfile.mkdtemp())
    s = Settings()
    cases = [("upload check, fixture policy", write_test_policy(d / "a"), ValidationLimits.from_settings(s, upload=True)),
             ("full, fixture policy", write_test_policy(d / "b", release_after_bias=2.0), ValidationLimits.from_settings(s)),
             ("full, conditional-NaN policy", conditional_nan_policy(d / "c.onnx"), ValidationLimits.from_settings(s)),
             ("full, 2 GiB memory-bomb policy", memory_bomb_policy(d / "m.onnx"), ValidationLimits.from_settings(s))]
    from sim_twin.provenance import short_commit

    commit = short_commit() or "unknown"
    out = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "commit": commit,
           "host": f"{platform.node()} ({platform.processor() or platform.machine()}, shared 2-core machine)",
           "command": "PYTHONPATH=$PWD MUJOCO_GL=egl python tests/benchmarks/bench_policy_validation.py",
           "cases": []}
    for name, path, limits in cases:
        t0 = time.monotonic()
        v = validate(path, limits)
        out["cases"].append({"case": name, "policy_sha256": sha256_of(path), "limits": v["limits"],
                             "wall_s": round(time.monotonic() - t0, 2), "passed": v["passed"], "reason": v["reason"],
                             "peak_rss_mib": round(v["peak_rss_bytes"] / 2**20), "observations": v["observations"],
                             "twin_throws": v["throws"]})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
