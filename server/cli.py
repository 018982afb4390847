"""The ``slinger`` command.

Subcommands::

    slinger up          the whole stack on this machine (server, 3D view, simulated machines, runtimes)
    slinger server      only the server (API + console + 3D view)
    slinger db upgrade  alembic upgrade head on the configured database
    slinger user add    add a user (the first admin: slinger user add --admin); user list
    slinger worker      a job worker (previews, evaluations, diagnoses)  (server.jobs.worker)
    slinger router      the site's Zenoh router              (server.site.router)
    slinger plant       the simulated machine            (sim_twin.twin.plant)
    slinger runtime     the runtime of one machine        (runtime.node)
    slinger ros2-bridge a ROS 2 machine behind the machine interface (runtime.ros2.bridge)
    slinger train       train a policy                   (sim_twin.training.train)
    slinger evaluate    evaluate a policy                (sim_twin.evaluation.cli)
    slinger diagnose    sim-to-real gap diagnosis        (sim_twin.diagnosis.cli)
    slinger adapt       adapt a policy to a diagnosed site (sim_twin.adaptation.adapt)
    slinger results     docs/results.md from the committed reports (server.site.results_page)

Settings not given as options come from ``SLINGER_*`` environment variables (server.config).
``up``, ``server``, ``db`` and ``user`` are built in; every other subcommand is provided by its
package through the entry-point group ``slinger.commands`` (:data:`COMMANDS`: ``runtime.commands``,
``sim_twin.commands``, ``server.commands``, declared in pyproject.toml and in each wheel's). Their
modules are imported only when that subcommand runs.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from importlib.metadata import EntryPoint, distributions
from pathlib import Path
from types import ModuleType

log = logging.getLogger("slinger")

COMMANDS = "slinger.commands"
"""Entry-point group of the subcommands that packages provide: each entry point is named after the
subcommand and loads a function that imports and returns the command's module (``main(argv)``, or
``build_parser``/``run``); the function's docstring is the help line."""


def sub_commands() -> dict[str, EntryPoint]:
    """The installed packages' subcommands (:data:`COMMANDS`), by name. Empty when Slinger is not
    installed (``pip install -e .`` registers them). Every distribution on the path counts, not only
    the first of a name: a checkout's build leftover ``slinger.egg-info`` in the working directory
    would otherwise hide the installed metadata (importlib.metadata's ``entry_points`` keeps one
    distribution per name)."""
    found: dict[str, EntryPoint] = {}
    for dist in distributions():
        for ep in dist.entry_points.select(group=COMMANDS):
            found.setdefault(ep.name, ep)
    return found


def load_command(ep: EntryPoint) -> tuple[Callable[[], ModuleType] | None, str]:
    """``(loader, help line)`` of a subcommand's entry point; ``(None, why)`` when the entry point
    does not load (a package's metadata names a function that is gone: reinstall)."""
    try:
        loader = ep.load()
    except (ImportError, AttributeError) as e:
        return None, f"unavailable: entry point {ep.value} does not load ({e}); reinstall Slinger"
    return loader, ((loader.__doc__ or "").strip().splitlines() or [""])[0]


def _settings(args: argparse.Namespace, **extra):
    from server.config import Settings

    overrides = {k: v for k, v in {
        "host": getattr(args, "host", None), "port": getattr(args, "port", None),
        "database_url": getattr(args, "database_url", None), "data_dir": getattr(args, "data_dir", None),
        "viser_port": getattr(args, "viser_port", None), **extra,
    }.items() if v is not None}
    return Settings(**overrides)


def _add_server_options(p: argparse.ArgumentParser, default_port: int = 8000) -> None:
    p.add_argument("--host", default=None, help="HTTP bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help=f"HTTP port (default {default_port})")
    p.add_argument("--viser-port", type=int, default=None, help="3D view port (default 8080; next free one if busy)")
    p.add_argument("--database-url", default=None, help="SQLAlchemy URL (default sqlite:///<data-dir>/slinger.db)")
    p.add_argument("--data-dir", type=Path, default=None, help="database, telemetry and logs (default ./var)")


def uvicorn_config(app, settings, log_level: str = "info"):
    """uvicorn's configuration for the app: its own proxy-header handling off (it trusts loopback
    by default, so any local client could pick its address through ``X-Forwarded-For``); the app
    applies ``Settings.trusted_proxies`` itself (server.app)."""
    import uvicorn

    return uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level, proxy_headers=False,
                          forwarded_allow_ips=[])


def _serve(settings, zenoh_session=None, on_started=None) -> int:
    """Run uvicorn in this thread until Ctrl-C/SIGTERM (uvicorn handles both gracefully)."""
    import uvicorn

    from server.app import create_app

    app = create_app(settings, zenoh_session=zenoh_session)
    server = uvicorn.Server(uvicorn_config(app, settings))
    if on_started is not None:
        def wait_started() -> None:
            while not server.started and not server.should_exit:
                time.sleep(0.1)
            if server.started:
                on_started(app)

        threading.Thread(target=wait_started, daemon=True).start()
    try:
        server.run()
    except KeyboardInterrupt:  # uvicorn re-raises the Ctrl-C it handled, after a clean shutdown
        log.info("stopped by Ctrl-C")
    return 0 if server.started else 1


def _print_urls(settings):
    def show(app) -> None:
        scene = app.state.scene
        print(f"Slinger console: http://{settings.host}:{settings.port}/", flush=True)
        if scene is not None:
            print(f"3D view:         http://{settings.viser_host}:{scene.port}/", flush=True)
        print(f"API docs:        http://{settings.host}:{settings.port}/docs", flush=True)

    return show


def cmd_up(args: argparse.Namespace) -> int:
    from runtime.zenoh_acl import site_acl
    from runtime.zenoh_session import TlsFiles, open_session
    from server.db.migrate import upgrade
    from server.site import stack
    from server.site.certs import make_site

    if args.ros2 is not None:  # refuse a bad mapping or a ROS 2 domain open beyond this host before starting anything
        from runtime.ros2.config import ConfigError
        from runtime.ros2.node import DomainRefused, machine_local_environment

        try:
            stack.ros2_domains(Path(args.ros2) if args.ros2 else None, args.machines)
            machine_local_environment(dict(os.environ))
        except (ConfigError, DomainRefused) as e:
            log.error("cannot start with --ros2: %s", e)
            return 2
    hub = f"tls/127.0.0.1:{args.zenoh_port}"
    settings = _settings(args, zenoh_listen=[hub])
    ids = stack.machine_ids(args.machines)
    site = make_site(settings.resolved_site_dir, ids)  # site CA, certificates, command keys (kept)
    policies, problems = {}, []
    for mode, given, default in (("2d", args.policy_2d, stack.DEFAULT_POLICY_2D),
                                 ("3d", args.policy_3d, stack.DEFAULT_POLICY_3D)):
        path, problem = stack.resolve_policy(given, default)
        if path is not None:
            policies[mode] = path
        elif given is not None or mode == "2d":
            problems.append(f"{mode}: {problem}")
    for p in problems:
        log.error("policy %s", p)
    if not policies:
        log.error("NOT starting any runtime: no usable policy. Train one (slinger train) and export it "
                  "to policies/throw2d.onnx + .json, or pass --policy-2d PATH. Server and simulated "
                  "machines start anyway; the console will show the runtimes offline.")
    upgrade(settings.database_url)
    from server.accounts.cli import ensure_local_admin

    ensure_local_admin(settings.database_url)
    if policies:
        stack.register_policies(settings.database_url, settings.data_dir, policies)
    children = stack.Children(stack_dir=settings.data_dir.resolve())
    with open_session(mode="peer", listen=(hub,), tls=TlsFiles.from_site(site.root, "server"),
                      access_control=site_acl(ids)) as session:
        try:
            from server.jobs.worker import worker_argv

            children.spawn("worker", worker_argv(settings), settings.data_dir / "logs")
            stack.spawn_machines(children, args.machines, hub, policies, settings.data_dir, site.root,
                                 settings.release_check_radius_m, engine=args.engine, ros2=False if args.ros2 is None else (Path(args.ros2) if args.ros2 else None))
            children.supervise()
            log.info("child logs in %s", settings.data_dir / "logs")
            return _serve(settings, zenoh_session=session, on_started=_print_urls(settings))
        finally:
            children.stop()


def cmd_server(args: argparse.Namespace) -> int:
    extra = {"zenoh_mode": args.zenoh_mode, "auto_migrate": args.migrate or None}
    if args.listen:
        extra["zenoh_listen"] = args.listen
    if args.connect:
        extra["zenoh_connect"] = args.connect
    if args.tls_dir:
        extra["zenoh_tls_dir"] = args.tls_dir
    settings = _settings(args, **{k: v for k, v in extra.items() if v is not None})
    return _serve(settings, on_started=_print_urls(settings))


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    from server.db.migrate import upgrade

    upgrade(_settings(args).database_url, args.revision)
    return 0


def _delegate(ep: EntryPoint, rest: list[str], prog: str) -> int:
    loader, why = load_command(ep)
    if loader is None:
        print(f"slinger: '{prog}' is {why}", file=sys.stderr)
        return 2
    try:
        module = loader()
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] == loader.__module__.split(".")[0]:
            print(f"slinger: '{prog}' is unavailable: {ep.value} imports {e.name}, which does not exist", file=sys.stderr)
        else:
            print(f"slinger: '{prog}' needs the missing package {e.name!r} (for training: pip install -e '.[train]')",
                  file=sys.stderr)
        return 2
    # The module's own main first: it is what `python -m <module>` runs, and it may do more than
    # parse and run (sim_twin.training.train re-launches itself under torchrun for --gpus N; the
    # diagnosis CLI parses options between positional arguments).
    if hasattr(module, "main"):
        return int(module.main(rest) or 0)
    if hasattr(module, "build_parser") and hasattr(module, "run"):
        parser = argparse.ArgumentParser(prog=f"slinger {prog}", description=(module.__doc__ or "").splitlines()[0] if module.__doc__ else None)
        module.build_parser(parser)
        return int(module.run(parser.parse_args(rest)) or 0)
    print(f"slinger: {module.__name__} has neither main nor build_parser/run", file=sys.stderr)
    return 2


ENGINES = ("mujoco", "drake")
"""Physics engines of the simulated machines (``slinger up --engine``), the names of
sim_twin.twin.engines.ENGINES as plain strings: a server-only install parses its command line without
sim_twin; the simulated machine's process (``slinger plant``) checks the name again where it runs it."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slinger", description="Slinger: dynamic throwing with material handlers")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    up = sub.add_parser("up", help="whole stack on this machine: server, a job worker, 3D view, simulated machines, runtimes")
    _add_server_options(up)
    up.add_argument("--zenoh-port", type=int, default=7447, help="port of the embedded Zenoh peer on 127.0.0.1 (default 7447)")
    up.add_argument("--machines", type=int, default=1, help="number of simulated machines, ids m1..mN (default 1)")
    up.add_argument("--policy-2d", type=Path, default=None, help="2D policy ONNX (default policies/throw2d.onnx in the repo)")
    up.add_argument("--policy-3d", type=Path, default=None, help="3D policy ONNX (default policies/throw3d.onnx if present)")
    up.add_argument("--engine", choices=ENGINES, default="mujoco",
                    help="physics engine of the simulated machines: mujoco (the twin) or drake (an independent engine; "
                         "needs the 'drake' extra)")
    up.add_argument("--ros2", nargs="?", const="", default=None, metavar="MAPPING",
                    help="each simulated machine as a ROS 2 driver node behind a ROS 2 bridge (rclpy; RMW_IMPLEMENTATION, "
                         "Fast DDS by default), with the bridge's mapping file (default: identity), machine i on ROS domain "
                         "base + i - 1 (docs/ros2.md)")
    up.set_defaults(func=cmd_up)

    srv = sub.add_parser("server", help="only the server: API, console, 3D view")
    _add_server_options(srv)
    srv.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    srv.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to, e.g. a router (repeatable)")
    srv.add_argument("--zenoh-mode", choices=("peer", "client"), default=None, help="Zenoh session mode (default peer)")
    srv.add_argument("--migrate", action="store_true", help="alembic upgrade head before serving")
    srv.add_argument("--tls-dir", type=Path, default=None,
                     help="site directory of `slinger certs`: Zenoh over mutual TLS (tls/ endpoints) with the site's access control")
    srv.set_defaults(func=cmd_server)

    db = sub.add_parser("db", help="database maintenance")
    db_sub = db.add_subparsers(dest="db_command", required=True)
    dbu = db_sub.add_parser("upgrade", help="alembic upgrade to head (or --revision)")
    dbu.add_argument("--database-url", default=None, help="SQLAlchemy URL (default from SLINGER_DATABASE_URL / settings)")
    dbu.add_argument("--data-dir", type=Path, default=None)
    dbu.add_argument("--revision", default="head")
    dbu.set_defaults(func=cmd_db_upgrade)

    from server.accounts.cli import build_parser as build_user_parser

    build_user_parser(sub)

    for name, ep in sorted(sub_commands().items()):
        if name in sub.choices:
            continue  # a built-in command keeps its name
        p = sub.add_parser(name, help=load_command(ep)[1], add_help=False)
        p.set_defaults(delegate=ep)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``slinger`` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
    if getattr(args, "delegate", None):
        return _delegate(args.delegate, rest, args.command)
    if rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
