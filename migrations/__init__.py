"""Alembic migrations of the Slinger database (env.py, versions/), shipped as a package so that
any install (``pip install .``, the slinger-server wheel, an editable install) finds them through
importlib.resources (server.db.migrate)."""
