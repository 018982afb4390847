"""``slinger user add|list``: manage accounts from the shell (the first admin comes from here,
or from ``slinger up``, which creates a local admin when there is no user at all)."""

from __future__ import annotations

import argparse
import getpass
import logging
import sys

log = logging.getLogger(__name__)


def build_parser(sub) -> None:
    """Add ``user`` with its subcommands to the ``slinger`` subparsers ``sub``."""
    user = sub.add_parser("user", help="accounts: add or list users")
    user_sub = user.add_subparsers(dest="user_command", required=True)
    add = user_sub.add_parser("add", help="add a user (the first admin: slinger user add --admin)")
    add.add_argument("username", nargs="?", default=None, help="user name (default 'admin' with --admin)")
    add.add_argument("--admin", action="store_true", help="role admin (policy versions, machines, users)")
    add.add_argument("--role", choices=("viewer", "operator", "admin"), default=None)
    add.add_argument("--password", default=None,
                     help="password (default: prompt on a terminal, else generate one and print it)")
    for p in (add, user_sub.add_parser("list", help="list users")):
        p.add_argument("--database-url", default=None)
        p.add_argument("--data-dir", default=None)
    add.set_defaults(func=cmd_user_add)
    user_sub.choices["list"].set_defaults(func=cmd_user_list)


def _sessions(args):
    from server.config import Settings
    from server.db.migrate import upgrade
    from server.db.session import make_engine, make_sessionmaker

    overrides = {k: v for k, v in {"database_url": args.database_url, "data_dir": args.data_dir}.items() if v}
    settings = Settings(**overrides)
    upgrade(settings.database_url)
    engine = make_engine(settings.database_url)
    return engine, make_sessionmaker(engine)


def cmd_user_add(args: argparse.Namespace) -> int:
    from server.accounts.auth import AuthError, audit, create_user, generate_password

    role = "admin" if args.admin else (args.role or "viewer")
    username = args.username or ("admin" if args.admin else None)
    if not username:
        print("slinger user add: give a user name (or --admin)", file=sys.stderr)
        return 2
    password, generated = args.password, False
    if password is None and sys.stdin.isatty():
        password = getpass.getpass(f"password for {username}: ")
    if not password:
        password, generated = generate_password(), True
    engine, sessions = _sessions(args)
    try:
        with sessions.begin() as db:
            create_user(db, username, password, role)
            audit(db, "cli", "user_add", username, role=role)
    except AuthError as e:
        print(f"slinger user add: {e}", file=sys.stderr)
        return 1
    finally:
        engine.dispose()
    print(f"added user {username} ({role})" + (f", password: {password}" if generated else ""))
    return 0


def cmd_user_list(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from server.db.models import User

    engine, sessions = _sessions(args)
    try:
        with sessions() as db:
            for u in db.scalars(select(User).order_by(User.username)):
                print(f"{u.username}\t{u.role}\t{'active' if u.active else 'inactive'}")
    finally:
        engine.dispose()
    return 0


def ensure_local_admin(database_url: str) -> None:
    """``slinger up``: create user ``admin`` with a random password if the database has no user,
    and print the credentials once (they are not stored anywhere in clear text)."""
    from server.accounts.auth import ensure_admin
    from server.db.session import make_engine, make_sessionmaker

    engine = make_engine(database_url)
    try:
        password = ensure_admin(make_sessionmaker(engine))
    finally:
        engine.dispose()
    if password is not None:
        print("Created the local admin account (shown only this once):", flush=True)
        print(f"  user: admin   password: {password}", flush=True)
