"""``slinger up``: the whole stack on one machine.

One process holds the server (FastAPI + viser) and an embedded Zenoh peer listening on
``tcp/127.0.0.1:<zenoh_port>``; per machine it spawns the simulated machine (``slinger plant``)
and its runtime (``slinger runtime``) as subprocesses that connect to that peer. The children
also listen on an ephemeral loopback port so that Zenoh gossip links plant and runtime directly
(peers do not forward for each other). :mod:`server.site.supervise` keeps the children: they die with
the stack (``kill -9`` included), are stopped on Ctrl-C/SIGTERM and restarted with back-off.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Literal

from runtime.release_check import DEFAULT_RADIUS_M
from server.site.supervise import Child, Children  # noqa: F401 (the stack's process supervision)
from sim_twin import default_policy

log = logging.getLogger(__name__)

DEFAULT_POLICY_2D = default_policy("2d")
DEFAULT_POLICY_3D = default_policy("3d")


def slinger_command(*args: str) -> list[str]:
    """The argv of ``slinger <args>`` run with this interpreter (works without the script on PATH)."""
    return [sys.executable, "-m", "server.cli", *args]


def resolve_policy(given: Path | None, default: Path) -> tuple[Path | None, str | None]:
    """(policy path, problem): the given or default ONNX file if it and its manifest exist."""
    path = given or default
    if not path.is_file():
        return None, f"no policy at {path}"
    if not path.with_suffix(".json").is_file():
        return None, f"policy {path} has no manifest {path.with_suffix('.json').name} beside it"
    return path, None


def machine_ids(n: int) -> list[str]:
    """Ids of the simulated machines: m1..mN."""
    return [f"m{i}" for i in range(1, n + 1)]


def ros2_domains(ros2: Path | None, n: int) -> list[int]:
    """ROS_DOMAIN_IDs of machines m1..mN behind ROS 2: the mapping's domain_id (else the
    environment's ROS_DOMAIN_ID, else 0) for m1, the next ones for the others (one domain per
    machine: every machine's driver publishes the same topic names).

    Raises:
        runtime.ros2.config.ConfigError: an unusable mapping file or a domain beyond 232.
    """
    import os

    from runtime.ros2.config import ConfigError, load

    base = (load(ros2).domain_id if ros2 else None)
    if base is None:
        try:
            base = int(os.environ.get("ROS_DOMAIN_ID", "").strip() or 0)
        except ValueError as e:
            raise ConfigError(f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']!r} is not a number") from e
    if not 0 <= base <= 232 - (n - 1):
        raise ConfigError(f"ROS domains {base}..{base + n - 1} of {n} machines: ROS_DOMAIN_ID must be 0..232")
    return [base + i for i in range(n)]


def spawn_machines(children: Children, n: int, hub: str, policies: dict[str, Path], data_dir: Path,
                   site_dir: Path | None = None, release_check_radius_m: float | None = DEFAULT_RADIUS_M,
                   ros2: Path | None | Literal[False] = False, engine: str = "mujoco") -> None:
    """Per machine: the simulated machine, and its runtime if any policy is given. The simulated
    machines run on the physics ``engine`` (sim_twin.twin.engines: "mujoco", or "drake" for an independent one).

    With ``ros2`` (a mapping file, or None for the identity mapping; False: off) the simulated
    machine is a ROS 2 driver node (``slinger plant --ros2``) and a ROS 2 bridge
    (``slinger ros2-bridge``) stands between it and the runtime, each machine on its own ROS
    domain (:func:`ros2_domains`).

    With ``site_dir`` (server.site.certs.make_site) every child uses mutual TLS and the site's access
    control (``--tls-dir``; ``hub`` and the children's own listeners are then ``tls/``
    endpoints) and each runtime gets its machine's command key (``--command-key``). Each runtime
    runs the release check at ``release_check_radius_m`` (None: off; server.config.Settings)."""
    log_dir = data_dir / "logs"
    ids = machine_ids(n)
    proto = "tls" if site_dir is not None else "tcp"
    tls = ["--tls-dir", str(site_dir), "--acl-machines", *ids] if site_dir is not None else []
    radius = ["--release-check-radius", "off" if release_check_radius_m is None else str(release_check_radius_m)]
    engine_arg = ["--engine", engine]
    domains = ros2_domains(ros2 or None, n) if ros2 is not False else []
    for i, mid in enumerate(ids):
        link = ["--connect", hub, "--listen", f"{proto}/127.0.0.1:0", *tls]
        if ros2 is False:
            children.spawn(f"plant-{mid}", slinger_command("plant", "--machine-id", mid, "--seed", str(i), *engine_arg, *link), log_dir)
        else:
            mapping, domain = ([str(ros2)] if ros2 else []), ["--domain-id", str(domains[i])]
            children.spawn(f"plant-{mid}", slinger_command("plant", "--machine-id", mid, "--seed", str(i), *engine_arg, "--ros2", *mapping,
                                                           *domain, *link), log_dir)
            children.spawn(f"ros2-bridge-{mid}", slinger_command("ros2-bridge", "--machine-id", mid, "--simulated",
                                                                 *(["--config", str(ros2)] if ros2 else []), *domain, *link), log_dir)
        if not policies:
            continue
        pol = [a for mode, p in sorted(policies.items()) for a in (f"--policy-{mode}", str(p))]
        key = ["--command-key", str(site_dir / "machines" / mid / "command.key")] if site_dir is not None else []
        children.spawn(f"runtime-{mid}", slinger_command(
            "runtime", "--machine-id", mid, *pol, *link, *key, *radius, "--outbox-dir", str(data_dir / "outbox" / mid)), log_dir)


def register_policies(database_url: str, data_dir: Path, policies: dict[str, Path]) -> None:
    """Record the deployed policy versions (with their manifests: the target range) in the DB."""
    import json

    from server.db.session import make_engine, make_sessionmaker
    from server.fleet.results import ResultStore

    engine = make_engine(database_url)
    try:
        store = ResultStore(make_sessionmaker(engine), data_dir)
        for path in policies.values():
            store.register_policy(json.loads(path.with_suffix(".json").read_text()), onnx_path=path)
    finally:
        engine.dispose()
