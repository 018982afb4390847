"""Build the three distributions from the repository without moving its folders.

    python packaging/build_wheels.py --out dist            # slinger-runtime, slinger-twin, slinger-server
    python packaging/build_wheels.py --out dist runtime    # only the runtime

Each package is staged in a temporary folder: its pyproject.toml from ``packaging/<name>/``,
its requirement files from ``packaging/requirements/`` (each dependency of the project is written
once there; the root pyproject.toml reads the same files), a ``VERSION`` file and the pins on
the sibling wheels (``requirements/slinger-*.txt``) from the root pyproject.toml's version, its
source folder from the repository (``runtime/``, ``sim_twin/``, ``server/``; the machine's MJCF
is the runtime's package data, runtime/dynamics/assets), and for the server the ``migrations``
package and the console pages (``server/web``, vendored scripts included). Then setuptools' PEP 517 backend of the running interpreter
builds the wheel (no build isolation, no network). The repository's own pyproject.toml stays the
all-in-one install.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

log = logging.getLogger("build_wheels")
REPO = Path(__file__).resolve().parent.parent
PACKAGES = {  # name -> (source folder, {extra copies: staged path <- repo path})
    "runtime": ("runtime", {}),
    "twin": ("sim_twin", {}),
    "server": ("server", {"migrations": "migrations", "server/web": "web"}),
}
IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
"""Build leftovers only: a pattern matches a name at every depth (``vendor`` once dropped the
console's web/vendor/uplot from the server wheel)."""
SIBLINGS = {"slinger-runtime": "slinger-runtime", "slinger-runtime-release-check": "slinger-runtime[release-check]",
            "slinger-twin": "slinger-twin"}
"""Pins on the sibling wheels, written into the staged ``requirements/<file>.txt`` (the twin's
MuJoCo comes with the runtime's release-check extra, written once; the server's API needs none)."""


def version() -> str:
    """The project's version (root pyproject.toml), shared by the three wheels."""
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]


def stage(name: str, into: Path) -> Path:
    """Copy package ``name``'s build files and sources into ``into``; returns ``into``.

    Raises:
        KeyError: unknown package name.
    """
    source, extra = PACKAGES[name]
    shutil.copy(REPO / "packaging" / name / "pyproject.toml", into / "pyproject.toml")
    shutil.copytree(REPO / "packaging" / "requirements", into / "requirements")
    v = version()
    (into / "VERSION").write_text(v + "\n")
    for file, requirement in SIBLINGS.items():
        (into / "requirements" / f"{file}.txt").write_text(f"{requirement}=={v}\n")
    (into / "README.md").write_text(f"Slinger {name} package, built from {REPO.name}/{source}.\n")
    shutil.copytree(REPO / source, into / source, ignore=IGNORE)
    for staged, original in extra.items():
        shutil.copytree(REPO / original, into / staged, ignore=IGNORE, dirs_exist_ok=True)
    return into


def build(name: str, out: Path) -> Path:
    """Build the wheel of ``name`` into ``out``; returns its path."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f"slinger-{name}-") as tmp:
        stage(name, Path(tmp))
        before = set(out.glob("*.whl"))
        code = f"from setuptools import build_meta; build_meta.build_wheel({str(out.resolve())!r})"
        subprocess.run([sys.executable, "-c", code], cwd=tmp, check=True, capture_output=True)
    wheels = sorted(set(out.glob(f"slinger_{name}-*.whl")) - before) or sorted(out.glob(f"slinger_{name}-*.whl"))
    log.info("built %s", wheels[-1].name)
    return wheels[-1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "dist", help="where the wheels go (default dist/)")
    p.add_argument("packages", nargs="*", help=f"some of {', '.join(PACKAGES)} (default all)")
    args = p.parse_args(argv)
    unknown = [n for n in args.packages if n not in PACKAGES]
    if unknown:
        p.error(f"unknown package(s) {unknown}; choose from {', '.join(PACKAGES)}")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in args.packages or PACKAGES:
        build(name, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
