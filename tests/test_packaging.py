"""Packages by where they run (packaging/): the runtime wheel installs alone with its light
dependencies and imports without MuJoCo, FastAPI, SQLAlchemy or viser; a non-editable install
of the server wheel runs ``slinger db upgrade`` on a fresh SQLite database.

Offline: the wheels are built from this checkout (packaging/build_wheels.py), and each fresh
virtual environment receives exactly the dependency closure of the package under test, linked
from the packages already installed in this interpreter (their files and ``.dist-info``), so
that ``pip check`` proves the declared requirements are met and anything undeclared is absent.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import re
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parent.parent
HEAVY = ("mujoco", "fastapi", "sqlalchemy", "viser", "sim_twin", "server", "torch", "jax")


def closure(requirements: list[str]) -> set[str]:
    """Names of the installed distributions ``requirements`` need, transitively (markers
    evaluated, extras of dependencies honoured, local slinger packages left out)."""
    seen: set[str] = set()
    todo = [Requirement(r) for r in requirements]
    while todo:
        req = todo.pop()
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        if name.startswith("slinger-") or name in seen or (req.marker and not req.marker.evaluate({"extra": ""})):
            continue
        seen.add(name)
        for sub in md.requires(name) or []:
            r = Requirement(sub)
            if r.marker is None or any(r.marker.evaluate({"extra": e}) for e in ("", *req.extras)):
                todo.append(Requirement(str(r).split(";")[0]))
    return seen


def make_venv(path: Path, dists: set[str]) -> Path:
    """A venv at ``path`` (no pip) with the files of ``dists`` linked into its site-packages."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True)
    site = next((path / "lib").glob("python3*/site-packages"))
    for name in dists:
        dist = md.distribution(name)
        tops = {Path(str(f)).parts[0] for f in dist.files or [] if not str(f).startswith("..")}
        for top in tops:
            src = Path(dist.locate_file(top))
            if src.exists() and not (site / top).exists():
                (site / top).symlink_to(src)
    return path / "bin" / "python"


def pip(python: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "--disable-pip-version-check",
                           *args], capture_output=True, text=True, timeout=300)


def declared(name: str) -> list[str]:
    return tomllib.loads((REPO / "packaging" / name / "pyproject.toml").read_text())["project"]["dependencies"]


@pytest.fixture(scope="module")
def wheels(tmp_path_factory) -> dict[str, Path]:
    sys.path.insert(0, str(REPO / "packaging"))
    try:
        from build_wheels import build
    finally:
        sys.path.pop(0)
    out = tmp_path_factory.mktemp("dist")
    return {name: build(name, out) for name in ("runtime", "server")}


def _clean_env() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}


def test_runtime_installs_alone_and_stays_light(wheels, tmp_path):
    python = make_venv(tmp_path / "venv", closure(declared("runtime")))
    r = pip(python, "install", "--no-index", "--no-deps", str(wheels["runtime"]))
    assert r.returncode == 0, r.stderr
    check = pip(python, "check")
    assert check.returncode == 0, check.stdout + check.stderr
    code = textwrap.dedent(f"""
        import importlib.util, sys
        import runtime, runtime.node, runtime.executor, runtime.controller, runtime.policy, runtime.outbox
        import runtime.protocol.messages, runtime.telemetry, runtime.ros2.bridge
        assert "site-packages" in runtime.__file__, runtime.__file__
        runtime.telemetry.write_mcap(runtime.telemetry.TelemetryRecorder())  # ROS 2 form: rosbags + the shipped URDF
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
        missing = [m for m in {HEAVY!r} if importlib.util.find_spec(m) is None]
        print("LOADED", loaded, "MISSING", missing)
    """)
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env=_clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "LOADED []" in out.stdout and f"MISSING {list(HEAVY)!r}" in out.stdout, out.stdout
    helped = subprocess.run([str(python.parent / "slinger-runtime"), "--help"], capture_output=True, text=True,
                            timeout=120, cwd=tmp_path, env=_clean_env())
    assert helped.returncode == 0 and "--machine-id" in helped.stdout, helped.stderr[-2000:]
    bridge = subprocess.run([str(python.parent / "slinger-ros2-bridge"), "--help"], capture_output=True, text=True,
                            timeout=120, cwd=tmp_path, env=_clean_env())
    assert bridge.returncode == 0 and "--config" in bridge.stdout, bridge.stderr[-2000:]


def test_server_wheel_runs_db_upgrade_without_the_repository(wheels, tmp_path):
    python = make_venv(tmp_path / "venv", closure(declared("server") + declared("runtime")))
    r = pip(python, "install", "--no-index", "--no-deps", str(wheels["runtime"]), str(wheels["server"]))
    assert r.returncode == 0, r.stderr
    check = pip(python, "check")
    assert check.returncode == 0, check.stdout + check.stderr
    db = tmp_path / "data" / "slinger.db"
    out = subprocess.run([str(python.parent / "slinger"), "db", "upgrade", "--database-url", f"sqlite:///{db}"],
                         capture_output=True, text=True, timeout=180, cwd=tmp_path, env=_clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "site-packages/server/migrations" in out.stderr or db.is_file()
    probe = subprocess.run([str(python), "-c", textwrap.dedent(f"""
        import sqlite3, sys
        import server.db.migrate as m, server.app as a
        assert "site-packages" in str(m.MIGRATIONS_DIR) and (a.WEB_DIR / "index.html").is_file(), (m.MIGRATIONS_DIR, a.WEB_DIR)
        tables = {{r[0] for r in sqlite3.connect({str(db)!r}).execute("select name from sqlite_master where type='table'")}}
        assert {{"throws", "jobs", "users", "alembic_version"}} <= tables, tables
        from server.mjcf_chain import KinematicChain, default_mjcf_path  # the 3D view's machine, without the twin
        assert "site-packages/server/assets" in str(default_mjcf_path()), default_mjcf_path()
        assert len(KinematicChain.from_mjcf().geom_poses([0.0] * 6)) == 7
        print("MUJOCO", "mujoco" in sys.modules)
    """)], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=_clean_env())
    assert probe.returncode == 0 and "MUJOCO False" in probe.stdout, probe.stderr[-3000:]
