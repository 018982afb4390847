"""Commands that default to the committed policies find them from any working directory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sim_twin import default_policy

REPO = Path(__file__).resolve().parents[1]


def test_default_policy_is_the_committed_file():
    assert default_policy("2d") == REPO / "policies" / "throw2d.onnx"
    assert default_policy("3d").is_file()
    with pytest.raises(ValueError, match="mode"):
        default_policy("4d")


def test_diagnose_generate_outside_the_repo_uses_the_committed_policy(tmp_path):
    """`slinger diagnose generate` run from another directory (it used to fail with 'policy file
    not found: policies/throw2d.onnx')."""
    env = dict(os.environ, PYTHONPATH=str(REPO), MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    out = tmp_path / "ds"
    proc = subprocess.run([sys.executable, "-m", "server.cli", "diagnose", "generate", "--mode", "2d", "--throws", "2",
                           "--workers", "1", "--out", str(out)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (out / "index.json").is_file()
