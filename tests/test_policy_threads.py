"""A policy session runs on the caller's thread: one intra-op thread, one inter-op thread, no
spin-waiting (runtime.policy.session_options), unless ``$SLINGER_POLICY_THREADS`` asks for more;
a bad value is refused with the variable's name.

onnxruntime's default is a pool of one thread per physical core spinning between calls: on a
64-core GPU host each of a site matrix's 14 workers held such a pool beside the training runs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from runtime.observation import observation_size
from runtime.policy import POLICY_THREADS_ENV, PolicyError, PolicyRunner
from tests.fixtures import write_test_policy

ROOT = Path(__file__).resolve().parents[1]


def test_loaded_policy_runs_single_threaded_without_spinning(tmp_path, monkeypatch):
    monkeypatch.delenv(POLICY_THREADS_ENV, raising=False)
    runner = PolicyRunner.load(write_test_policy(tmp_path))
    opts = runner._session.get_session_options()
    assert opts.intra_op_num_threads == 1
    assert opts.inter_op_num_threads == 1
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert np.all(np.isfinite(runner.act(np.zeros(observation_size("2d"), dtype=np.float32))))


@pytest.mark.parametrize("setting, spinning", [("3", "0"), ("0", "")])
def test_threads_from_the_environment(tmp_path, monkeypatch, setting, spinning):
    """N threads without spinning; 0: onnxruntime's defaults (its pool size 0 = a thread per
    physical core, spinning not switched off)."""
    monkeypatch.setenv(POLICY_THREADS_ENV, setting)
    runner = PolicyRunner.load(write_test_policy(tmp_path))
    opts = runner._session.get_session_options()
    assert opts.intra_op_num_threads == int(setting)
    try:
        entry = opts.get_session_config_entry("session.intra_op.allow_spinning")
    except RuntimeError:  # not set
        entry = ""
    assert entry == spinning


@pytest.mark.parametrize("bad", ["two", "-1", "1.5", ""])
def test_bad_thread_count_is_refused_by_name(tmp_path, monkeypatch, bad):
    onnx_path = write_test_policy(tmp_path)
    before = onnx_path.read_bytes()
    monkeypatch.setenv(POLICY_THREADS_ENV, bad)
    with pytest.raises(PolicyError, match=POLICY_THREADS_ENV):
        PolicyRunner.load(onnx_path)
    assert onnx_path.read_bytes() == before


_COUNT_THREADS = """
import json, os, sys
from runtime.policy import PolicyRunner
def threads():
    return len(os.listdir(f"/proc/{os.getpid()}/task"))
runners = [PolicyRunner.load(sys.argv[1])]  # the first also starts onnxruntime's own threads
before = threads()
runners += [PolicyRunner.load(sys.argv[1]) for _ in range(3)]
print(json.dumps({"before": before, "after": threads()}))
"""


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads through /proc")
@pytest.mark.parametrize("setting, extra_per_session", [("1", 0), ("4", 3)])
def test_sessions_start_the_threads_asked_for(tmp_path, setting, extra_per_session):
    """Three more loaded policies in a process start no thread of their own at the default; with
    4 intra-op threads each starts 3 (the caller's thread is the fourth)."""
    onnx_path = write_test_policy(tmp_path)
    env = {**os.environ, POLICY_THREADS_ENV: setting, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _COUNT_THREADS, str(onnx_path)], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    counts = json.loads(out.strip().splitlines()[-1])
    assert counts["after"] - counts["before"] == 3 * extra_per_session
