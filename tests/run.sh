#!/usr/bin/env bash
# Install everything the tests need on a fresh machine and run them (README's test command).
# Creates .venv, installs the CPU build of PyTorch 2.13.0 (from local disk) and Slinger with its
# training and test extras, installs Debian's Chromium for the browser tests, makes sure the local
# PostgreSQL and Redis are up (PostgreSQL migration and site job-queue tests), runs the static checks
# (ruff, mypy, import-linter's layer contract; configured in pyproject.toml), then pytest.
# The fast tier alone, after `pip install -e ".[test]"` (no torch, services, Chromium or root; two
# pytest-xdist processes; docs/development.md: test tiers):
#   python -m pytest -m "not system" -n 2 --dist loadfile
set -euo pipefail
cd "$(dirname "$0")/.."

python3 -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
# --no-compile: no bytecode for every file of every package at install (about 45 s on 2 cores);
# Python compiles the modules the tests import on first use.
python -m pip install -q --no-compile torch==2.13.0
# the ros2 extra: ROS 2 (Kilted) as PyPI wheels, rclpy on Fast DDS, for the ROS 2 bridge's system
# tests (tests/test_ros2_bridge.py); ros-wheels-bootstrapper sets their library path itself
python -m pip install -q --no-compile -e ".[train,test,lint,ros2]"

if [ ! -x /usr/bin/chromium ]; then
  export DEBIAN_FRONTEND=noninteractive
  apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; }
fi

if command -v pg_isready >/dev/null && ! pg_isready -q -h 127.0.0.1 -p 5432; then
  pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql)" main start || true
fi

# Redis (the site job queue test): start the local server if it is installed but not answering.
if command -v redis-cli >/dev/null && ! redis-cli -h 127.0.0.1 -p 6379 ping >/dev/null 2>&1; then
  command -v redis-server >/dev/null && redis-server --bind 127.0.0.1 --port 6379 --daemonize yes >/dev/null || true
fi

ruff check
mypy
lint-imports

export MUJOCO_GL=egl
if [ $# -gt 0 ]; then exec python -m pytest -q --durations=25 "$@"; fi
# The whole suite in three runs: the fast tier on two processes (its tests are safe in parallel,
# docs/development.md#test-tiers); the system tier's training tests (torch and no other system marker:
# CPU-bound JAX and PyTorch work with no process, browser, service or real-time bound) on two processes
# too (quiet 2-core host, JAX's compilation cache warm: 9.1 min in one process, 6.1 in two; from a fresh
# clone, whose cache misses, 13.6 in two); then the rest of the system tier in one (its
# processes, stacks and real-time limits would compete for the cores).
TRAINING_ONLY="torch and not (browser or processes or root or postgres or redis or slow or acceptance)"
python -m pytest -q -m "not system" -n 2 --dist loadfile
python -m pytest -q -m "$TRAINING_ONLY" -n 2 --dist loadfile --durations=10
python -m pytest -q -m "system and not ($TRAINING_ONLY)" --durations=25
