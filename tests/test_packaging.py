"""Packages by where they run (packaging/): the runtime wheel installs alone with its light
dependencies and imports without MuJoCo, FastAPI, SQLAlchemy or viser; a non-editable install
of the server wheel runs ``slinger db upgrade`` on a fresh SQLite database and serves every file
the console pages load; each requirement is written once (packaging/requirements/).

Offline: the wheels are built from this checkout (packaging/build_wheels.py), and each fresh
virtual environment receives exactly the dependency closure of the package under test, linked
from the packages already installed in this interpreter (their files and ``.dist-info``), so
that ``pip check`` proves the declared requirements are met and anything undeclared is absent.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import re
import shutil
import socket
import sqlite3
import subprocess
import sys
import textwrap
import time
import tomllib
import urllib.request
from html.parser import HTMLParser
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


def requirement_files(pyproject: Path, extra: str | None = None) -> list[Path]:
    """The requirement files that ``pyproject`` reads its dependencies (or ``extra``'s) from
    (``[tool.setuptools.dynamic]``), as files of packaging/requirements/; the pins on the sibling
    slinger wheels, written by packaging/build_wheels.py when it stages, left out."""
    dynamic = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["dynamic"]
    entry = dynamic["dependencies"] if extra is None else dynamic["optional-dependencies"][extra]
    return [REPO / "packaging" / "requirements" / Path(f).name for f in entry["file"]
            if not Path(f).name.startswith("slinger-")]


def read_requirements(files: list[Path]) -> list[str]:
    """The requirements in ``files`` (one a line; blank and ``#`` lines skipped, as setuptools does)."""
    return [line.strip() for f in files for line in f.read_text().splitlines()
            if line.strip() and not line.strip().startswith("#")]


def declared(name: str, extra: str | None = None) -> list[str]:
    """The requirements of the root pyproject.toml (``name`` "root") or of packaging/<name>/."""
    pyproject = REPO / "pyproject.toml" if name == "root" else REPO / "packaging" / name / "pyproject.toml"
    return read_requirements(requirement_files(pyproject, extra))


def test_each_requirement_is_written_once():
    """packaging/requirements/*.txt hold every requirement once; the root install is the union
    of the three wheels (runtime with its release check, twin, server)."""
    seen: dict[str, Path] = {}
    for f in sorted((REPO / "packaging" / "requirements").glob("*.txt")):
        for r in read_requirements([f]):
            name = re.sub(r"[-_.]+", "-", Requirement(r).name).lower()
            assert name not in seen, f"{name} in both {seen[name].name} and {f.name}"
            seen[name] = f
    wheels = declared("runtime") + declared("runtime", "release-check") + declared("twin") + declared("server")
    assert sorted(declared("root")) == sorted(wheels)


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
        # without MuJoCo (the 'release-check' extra) the release check names the reason, and the
        # executor refuses every throw with it unless the check is off
        from runtime.dynamics import MJCF_PATH
        from runtime.executor import ExecutorConfig, ThrowExecutor
        from runtime.protocol.messages import MachineState, ThrowRequest
        from runtime.policy import PolicyRunner
        from runtime.release_check import ReleaseCheck
        assert MJCF_PATH.is_file() and "site-packages" in str(MJCF_PATH), MJCF_PATH
        check = ReleaseCheck.load()
        assert check.predictor is None and "mujoco" in check.unavailable, check
        state = MachineState(machine_id="m1", stamp_s=1.0, q=[0.0] * 6, qd=[0.0] * 6, gripper_open=False,
                             payload_attached=True)
        req = ThrowRequest(throw_id="t", machine_id="m1", mode="2d", target_m=[8.0, 0.0, 0.0])
        refusal = ThrowExecutor({{"2d": PolicyRunner.load({str(REPO / "policies" / "throw2d.onnx")!r})}},
                                release_check=check).start(req, state)
        print("REFUSAL", refusal)
    """)
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env=_clean_env())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "LOADED []" in out.stdout and f"MISSING {list(HEAVY)!r}" in out.stdout, out.stdout
    assert "REFUSAL release check unavailable (ModuleNotFoundError: No module named 'mujoco')" in out.stdout, out.stdout
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
    assert db.is_file(), out.stderr[-3000:]
    probe = subprocess.run([str(python), "-c", textwrap.dedent(f"""
        import sqlite3, sys
        import server.db.migrate as m, server.app as a
        assert "site-packages" in str(m.migrations_dir()) and (a.WEB_DIR / "index.html").is_file(), (m.migrations_dir(), a.WEB_DIR)
        tables = {{r[0] for r in sqlite3.connect({str(db)!r}).execute("select name from sqlite_master where type='table'")}}
        assert {{"throws", "jobs", "users", "alembic_version"}} <= tables, tables
        from server.console.mjcf_chain import KinematicChain, default_mjcf_path  # the 3D view's machine, without the twin
        assert "site-packages/runtime/dynamics/assets" in str(default_mjcf_path()), default_mjcf_path()
        assert len(KinematicChain.from_mjcf().geom_poses([0.0] * 6)) == 7
        print("MUJOCO", "mujoco" in sys.modules)
    """)], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=_clean_env())
    assert probe.returncode == 0 and "MUJOCO False" in probe.stdout, probe.stderr[-3000:]


class _Assets(HTMLParser):
    """The local scripts, stylesheets and icons a console page references."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: list[str] = []

    def handle_starttag(self, tag, attrs) -> None:
        a = dict(attrs)
        ref = a.get("src") if tag == "script" else a.get("href") if tag == "link" else None
        if ref and not re.match(r"^(https?:|data:|//|/)", ref):
            self.refs.append(ref)


def test_server_wheel_serves_every_console_asset(wheels, tmp_path):
    """`slinger server` from the installed wheel (no repository on the path) serves every console
    page and every script, stylesheet and icon the pages reference (web/vendor/uplot included)."""
    python = make_venv(tmp_path / "venv", closure(declared("server") + declared("runtime")))
    r = pip(python, "install", "--no-index", "--no-deps", str(wheels["runtime"]), str(wheels["server"]))
    assert r.returncode == 0, r.stderr
    ports = []
    for _ in range(3):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    http, viser, zenoh = ports
    log = (tmp_path / "server.log").open("w")
    proc = subprocess.Popen([str(python.parent / "slinger"), "server", "--migrate", "--port", str(http),
                             "--viser-port", str(viser), "--data-dir", str(tmp_path / "data"),
                             "--listen", f"tcp/127.0.0.1:{zenoh}"],
                            stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, env=_clean_env())
    base = f"http://127.0.0.1:{http}/console/"
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                urllib.request.urlopen(base + "login.html", timeout=2).read()
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "server.log").read_text()[-3000:]
                time.sleep(0.3)
        pages = sorted(p.name for p in (REPO / "web").glob("*.html") if not p.name.startswith("_"))  # _*.html: partials the pages include
        loaded: set[str] = set()
        for page in pages:
            parser = _Assets()
            parser.feed(urllib.request.urlopen(base + page, timeout=10).read().decode())
            for ref in parser.refs:
                with urllib.request.urlopen(base + ref.split("?")[0], timeout=10) as resp:
                    assert resp.status == 200 and resp.read(), (page, ref)
                loaded.add(ref)
        assert "vendor/uplot/uPlot.iife.min.js" in loaded and "vendor/uplot/uPlot.min.css" in loaded, loaded
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def test_root_install_runs_db_upgrade(tmp_path):
    """`pip install .` (not editable) of the all-in-one root package migrates: the migrations are
    a package of the wheel, found through importlib.resources, not a folder beside server/."""
    src = tmp_path / "src"
    for part in ("runtime", "sim_twin", "server", "migrations", "packaging/requirements"):
        shutil.copytree(REPO / part, src / part, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for f in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / f, src / f)
    out = tmp_path / "dist"
    code = f"from setuptools import build_meta; print(build_meta.build_wheel({str(out)!r}))"
    out.mkdir()
    subprocess.run([sys.executable, "-c", code], cwd=src, check=True, capture_output=True, timeout=300)
    wheel = next(out.glob("slinger-*.whl"))
    python = make_venv(tmp_path / "venv", closure(declared("server") + declared("runtime")))
    r = pip(python, "install", "--no-index", "--no-deps", str(wheel))
    assert r.returncode == 0, r.stderr
    db = tmp_path / "data" / "slinger.db"
    done = subprocess.run([str(python.parent / "slinger"), "db", "upgrade", "--database-url", f"sqlite:///{db}"],
                          capture_output=True, text=True, timeout=180, cwd=tmp_path, env=_clean_env())
    assert done.returncode == 0, done.stderr[-3000:]
    assert db.is_file() and "alembic_version" in {
        row[0] for row in sqlite3.connect(db).execute("select name from sqlite_master where type='table'")}


def _docker_sources(dockerfile: Path) -> list[str]:
    """The build-context paths the Dockerfile's COPY instructions read (not those from a stage)."""
    sources = []
    for line in dockerfile.read_text().splitlines():
        words = line.split()
        if words[:1] == ["COPY"] and not any(w.startswith("--from") for w in words):
            sources += [w for w in words[1:-1] if not w.startswith("--")]
    return sources


def test_dockerfile_copies_what_the_wheels_need():
    """No Docker engine here: the Dockerfile is checked by reading. Every file it COPYs exists and
    is not excluded by its .dockerignore; it builds what packaging/build_wheels.py stages and
    installs the image from those wheels (no editable install); compose.yaml's policy paths are in it."""
    dockerfile = REPO / "docker" / "Dockerfile"
    sources = _docker_sources(dockerfile)
    ignored = {line.strip() for line in (REPO / "docker" / "Dockerfile.dockerignore").read_text().splitlines()}
    for src in sources:
        assert (REPO / src).exists(), f"Dockerfile copies {src}, which is not in the repository"
        assert src.rstrip("/") not in ignored, f"Dockerfile copies {src}, which .dockerignore excludes"
    sys.path.insert(0, str(REPO / "packaging"))
    try:
        import build_wheels
    finally:
        sys.path.pop(0)
    staged = {"pyproject.toml", "packaging"} | {src for src, extra in build_wheels.PACKAGES.values()} | {
        original.split("/")[0] for _, extra in build_wheels.PACKAGES.values() for original in extra.values()}
    assert staged <= set(sources), f"the wheel stage lacks {staged - set(sources)}"
    text = dockerfile.read_text()
    assert "build_wheels.py" in text and "pip install -e" not in text
    for wheel in ("slinger-runtime[release-check]", "slinger-twin", "slinger-server[worker,redis]"):
        assert wheel in text
    compose = (REPO / "docker" / "compose.yaml").read_text()
    for path in re.findall(r"/app/(policies/[\w.]+)", compose):
        assert (REPO / path).is_file() and "policies" in sources, path
